"""Unsupervised loss terms (registration, ARAP, geodesic distortion) and WeightedLoss."""
