"""Scenes (COLMAP, synthetic), splits, paired-clip preparation, cache and the PairedClipDataModule."""
