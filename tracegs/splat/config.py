"""Hyperparameters of the 3DGS optimiser and of the deployment trajectories (embedded-scale defaults).

Paper scale (3DGS / gsplat defaults, 30k iterations): iterations=30000, snapshot_iters=[7000, 17000, 30000],
sh_degree_interval=1000, refine_start_iter=500, refine_stop_iter=15000, refine_every=100, reset_every=3000,
grow_grad2d=0.0002, max_gaussians=10_000_000 (no budget in practice),
lr_means=1.6e-4, lr_means_final=1.6e-6, lr_scales=5e-3, lr_opacities=5e-2, lr_sh_dc=2.5e-3, lr_sh_rest=1.25e-4,
lr_quats=1e-3, backend="auto" (gsplat on CUDA). Trajectory: frames_per_clip=49.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class DensificationConfig:
    """gsplat `DefaultStrategy` settings (3DGS's adaptive density control), iterations 0-based."""

    enabled: bool = True
    refine_start_iter: int = 50
    refine_stop_iter: int = 450
    refine_every: int = 25
    reset_every: int = 200
    grow_grad2d: float = 0.002  # 3DGS uses 0.0002 at full resolution; at 48x72 that grows ~10x too many
    grow_scale3d: float = 0.01
    prune_opa: float = 0.005
    prune_scale3d: float = 0.1
    max_gaussians: int = 8000  # keep the most opaque ones beyond this budget (bounds the CPU cost per step)


@dataclass
class GaussianFitConfig:
    """3DGS optimisation: (1 - ssim_weight) L1 + ssim_weight D-SSIM per view, Adam with per-parameter rates.

    `lr_means` and `lr_means_final` are multiplied by the scene extent and decay exponentially over
    `iterations`; the other rates are constant. The SH degree grows by one every `sh_degree_interval`
    iterations up to `sh_degree`.
    """

    iterations: int = 600
    snapshot_iters: list[int] = field(default_factory=lambda: [140, 340, 600])
    lr_means: float = 1.6e-3
    lr_means_final: float = 1.6e-5
    lr_quats: float = 5e-3
    lr_scales: float = 1e-2
    lr_opacities: float = 5e-2
    lr_sh_dc: float = 1e-2
    lr_sh_rest: float = 5e-4
    ssim_weight: float = 0.2
    ssim_window: int = 11
    sh_degree: int = 3
    sh_degree_interval: int = 100
    background: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    backend: str = "auto"
    seed: int = 0
    init_num_points: int = 2000
    keep_freed_cpu_memory: bool = True  # glibc keeps freed pages: ~20% faster CPU steps (see fit.py)
    densification: DensificationConfig = field(default_factory=DensificationConfig)


@dataclass
class TrajectoryConfig:
    """Deployment trajectory of supplement A.5: a 360-degree ellipse around the focus point whose scale and
    vertical variation depend on the repair round, with a random vertical phase, joined to the reference views
    by bridge poses. Round r (0-based) uses scale `ellipse_scales[r]` and height variation
    `height_variations[r]` (the last entry repeats for later rounds)."""

    frames_per_clip: int = 9
    ellipse_scales: list[float] = field(default_factory=lambda: [1.0, 0.85, 0.7])
    height_variations: list[float] = field(default_factory=lambda: [0.05, 0.1, 0.15])
    ellipse_frames: int = 64
