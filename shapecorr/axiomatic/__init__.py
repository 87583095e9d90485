"""Axiomatic matching: optimization methods without training (Smooth Shells, divergence-free interpolation)."""
