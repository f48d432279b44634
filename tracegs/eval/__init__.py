"""Evaluation: metrics and reports (tables, plots, videos)."""
