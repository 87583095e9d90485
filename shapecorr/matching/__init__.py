"""Matching: Sinkhorn, least squares, the Deep Shells layer, softmax correspondences, baselines, MatchResult."""
