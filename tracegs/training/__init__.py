"""Training: losses, baseline (A) module, Stage 1 alignment, Stage 2 on-policy distillation."""
