"""Gaussian splatting engine: scene model, cameras, rasterizer backends, 3DGS optimiser, trajectories, PLY io.

Modules (import them directly; this package file imports nothing so configs stay light):
- `cameras`: `Camera` (OpenCV convention), `Camera.look_at`, `.rescaled`, `.center`, `.rotation`.
- `gaussians`: `GaussianModel` (means, quats, log_scales, opacity_logits, sh_dc, sh_rest), `from_points`,
  `random`.
- `render`: `render(model, camera, background, sh_degree, backend)` -> `RenderOutput(image, alpha, depth, info)`;
  backends "compiled" (`preprocess_compiled.py` + `rasterize_compiled.py`, CPU), "torch" (tile-culled,
  `rasterize.py`), "dense" (reference), "gsplat" (CUDA), "auto".
- `fit`: `View`, `GaussianFitter` (train_until with pseudo-observation weight), `fit_gaussians`.
- `trajectory`: `focus_point`, `ellipse_poses`, `bridge_poses`, `make_clip`, `round_trajectory`.
- `ply`: `save_ply`, `load_ply` (reference 3DGS layout).
- `config`: `GaussianFitConfig`, `DensificationConfig`, `TrajectoryConfig`.
"""
