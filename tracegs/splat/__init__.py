"""Gaussian splatting engine: scene model, cameras, rasterizer backends, 3DGS optimiser, trajectories, PLY io."""
