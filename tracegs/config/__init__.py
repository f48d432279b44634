"""Typed Hydra config schema and cross-field validation."""
