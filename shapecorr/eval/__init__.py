"""Evaluation: metrics, scoring, the per-pair protocol, records, worker pool, sharding, reports, export."""
