"""Evaluation: scoring deployed scenes, merging shards, metrics and reports (tables, plots, videos)."""
