"""Evaluation: metrics, the per-pair protocol, reports, map and sequence export."""
