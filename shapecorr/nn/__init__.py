"""Networks and building blocks (spectral filter bank, EdgeConv, NeuroMorph networks) and the Backbone interface."""
