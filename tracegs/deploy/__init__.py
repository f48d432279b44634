"""Deployment: the restore-refine loop (Algorithm 1 bottom), its restorers and the per-scene deployment run."""
