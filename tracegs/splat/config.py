"""Hyperparameters of the 3DGS optimiser and of the deployment trajectories (embedded-scale defaults).

Paper scale: ``conf/splat/paper.yaml`` (the reference 3DGS optimiser, 30k iterations).
"""

from __future__ import annotations

from dataclasses import dataclass

from tracegs.errors import ConfigError
from tracegs.modes import Mode
from tracegs.products import EVERY, reads
from tracegs.ranges import FINITE, SEED, at_least, check_ranges, each, positive, within


class RenderBackend(Mode):
    """The rasterizer (tracegs.splat.render)."""

    auto = "auto"  # gsplat where CUDA and the package are present, else compiled (refused where it cannot build)
    compiled = "compiled"  # the tiled rasterizer compiled to one C++ loop per pixel (CPU)
    torch = "torch"  # tiled pure-PyTorch rasterizer (readable reference; any device)
    dense = "dense"  # every Gaussian on every pixel (small images; the reference for the tiled one)
    gsplat = "gsplat"  # CUDA only


@dataclass
class DensificationConfig:
    """gsplat `DefaultStrategy` settings (3DGS's adaptive density control), iterations 0-based."""

    enabled: bool = reads(EVERY, default=True)
    refine_start_iter: int = reads(EVERY, default=50, range=at_least(0))
    refine_stop_iter: int = reads(EVERY, default=450, range=at_least(0))
    refine_every: int = reads(EVERY, default=25, range=at_least(1))
    reset_every: int = reads(EVERY, default=200, range=at_least(1))
    # 3DGS uses 0.0002 at full resolution; at 48x72 that grows ~10x too many
    grow_grad2d: float = reads(EVERY, default=0.002, range=positive())
    grow_scale3d: float = reads(EVERY, default=0.01, range=positive())
    prune_opa: float = reads(EVERY, default=0.005, range=within(0, 1))
    prune_scale3d: float = reads(EVERY, default=0.1, range=positive())
    # Prune Gaussians whose screen radius exceeded this many pixels, from the first opacity reset on (the
    # reference optimiser and GSFixer's release: train.py l. 246, ``size_threshold = 20 if iteration >
    # opacity_reset_interval``); None = no screen pruning (gsplat's default, the embedded scale's measured one).
    screen_prune_px: float | None = reads(EVERY, default=None, range=positive())
    # Not in the reference optimiser: keep the most opaque Gaussians beyond this budget (bounds the CPU cost
    # per step at the embedded scale); None = no cap (paper scale).
    max_gaussians: int | None = reads(EVERY, default=8000, range=at_least(1))


class PseudoSsim(Mode):
    """Which SSIM the pseudo-view term L_pseudo of deployment's refinement uses (tracegs.splat.fit)."""

    # GSFixer's release (train.py l. 212): ``ssim(image, gt_image)``, the captured view's render against its
    # image, reused; the pseudo view contributes only its L1.
    captured = "captured"
    # Corrected: D-SSIM of the pseudo view's render against its restored frame.
    pseudo = "pseudo"


@dataclass
class GaussianFitConfig:
    """3DGS optimisation: (1 - ssim_weight) L1 + ssim_weight D-SSIM per view, Adam with per-parameter rates.

    `lr_means` and `lr_means_final` are multiplied by the scene extent and decay exponentially over
    `iterations`; the other rates are constant. The SH degree grows by one every `sh_degree_interval`
    iterations up to `sh_degree`.
    """

    iterations: int = reads(EVERY, default=600, range=at_least(1))
    snapshot_iters: list[int] = reads(EVERY, factory=lambda: [140, 340, 600], range=each(at_least(1)))
    lr_means: float = reads(EVERY, default=1.6e-3, range=positive())
    lr_means_final: float = reads(EVERY, default=1.6e-5, range=positive())
    lr_quats: float = reads(EVERY, default=5e-3, range=at_least(0))
    lr_scales: float = reads(EVERY, default=1e-2, range=at_least(0))
    # The reference optimiser's opacity rate; GSFixer's release halves it (arguments/__init__.py l. 115: 0.025).
    lr_opacities: float = reads(EVERY, default=5e-2, range=at_least(0))
    lr_sh_dc: float = reads(EVERY, default=1e-2, range=at_least(0))
    lr_sh_rest: float = reads(EVERY, default=5e-4, range=at_least(0))
    ssim_weight: float = reads(EVERY, default=0.2, range=within(0, 1))
    ssim_window: int = reads(EVERY, default=11, range=at_least(1))
    sh_degree: int = reads(EVERY, default=3, range=within(0, 3))
    sh_degree_interval: int = reads(EVERY, default=100, range=at_least(1))
    background: list[float] = reads(EVERY, factory=lambda: [0.0, 0.0, 0.0], range=each(within(0, 1)))
    backend: RenderBackend = reads(EVERY, default=RenderBackend.auto)
    seed: int = reads(EVERY, default=0, range=SEED)
    init_num_points: int = reads(EVERY, default=2000, range=at_least(1))
    # The SfM points a fit starts from: those seen by at least this many of its views. 2 = what the view set
    # would triangulate itself (no geometry from views it never saw); GSFixer's release keeps every point any
    # sparse view observes, 1 (datasets/colmap_debug.py l. 354-369, ``filter_points_sparse``).
    init_min_views: int = reads(EVERY, default=2, range=at_least(1))
    # glibc keeps freed pages: ~20% faster CPU steps (see fit.py)
    keep_freed_cpu_memory: bool = reads(EVERY, default=True)
    densification: DensificationConfig = reads(EVERY, factory=DensificationConfig)
    # Deployment's pseudo-view term (Eq. supp-refinement-objective): its SSIM pair, and whether the pseudo view's
    # screen-space gradients feed densification (GSFixer's release: no, train.py l. 198-202 and 243 keep the
    # captured view's ``viewspace_points``). Embedded default: the corrected protocol.
    pseudo_ssim: PseudoSsim = reads(EVERY, default=PseudoSsim.pseudo)
    pseudo_densification: bool = reads(EVERY, default=True)

    def sh_degree_at(self, iteration: int) -> int:
        """The SH degree in use at ``iteration``: one band more every ``sh_degree_interval``, up to
        ``sh_degree`` (reference 3DGS)."""
        return min(self.sh_degree, iteration // max(self.sh_degree_interval, 1))


class ClipRule(Mode):
    """How a repair round's trajectory is cut into clips (tracegs.splat.trajectory.round_clips)."""

    # One clip per pair of reference views chained in capture order, its middle the ellipse arc between them.
    reference_pairs = "reference_pairs"
    # GSFixer's release (gsfixer/extrapolation/outpaint/sparse.py l. 236-283): the round's ellipse cut into
    # overlapping windows of consecutive poses, each bridged from and to its nearest captured view.
    gsfixer_windows = "gsfixer_windows"


class EllipseFrame(Mode):
    """Where GSFixer's ellipse (``clip_rule=gsfixer_windows``) is laid (tracegs.splat.trajectory)."""

    # GSFixer's release (gsfixer/extrapolation/outpaint/sample_utils.py l. 154-183, in its normalised world,
    # datasets/normalize.py): centred on 1.2 x the focus point's world xy, heights in absolute world z.
    gsfixer_world = "gsfixer_world"
    # Corrected: centred on the focus point, on the cameras' principal axes, heights above the focus.
    focus = "focus"


@dataclass
class TrajectoryConfig:
    """Deployment trajectory of supplement A.5: a 360-degree ellipse around the focus point whose scale and
    vertical variation depend on the repair round, with a random vertical phase, joined to the reference views
    by bridge poses. Round r (0-based) uses scale `ellipse_scales[r]`, height variation `height_variations[r]`
    and pitch `pitch_degrees[r]`, one entry per repair round, cycling beyond them (prepare renders many rounds).
    The supplement states that scale and height depend on the round but not their values: the embedded ones are
    unstated choices, the paper scale takes GSFixer's (conf/deploy/paper.yaml). Their meaning follows
    `clip_rule`: with ``reference_pairs`` the scale multiplies the cameras' horizontal spread and the height
    variation is an amplitude in mean camera distances; with ``gsfixer_windows`` the scale multiplies the
    cameras' 90th-percentile horizontal offset and the height variation multiplies their 10th-90th percentile
    height band (``release_ellipse``, ``focus_ellipse``). Prepare and deployment read this one config (``data.prepare.trajectory``
    is ``deploy.trajectory``)."""

    frames_per_clip: int = reads(EVERY, default=9, range=at_least(1))
    ellipse_scales: list[float] = reads(EVERY, factory=lambda: [1.0, 0.85, 0.7], range=each(positive()))
    height_variations: list[float] = reads(EVERY, factory=lambda: [0.05, 0.1, 0.15], range=each(at_least(0)))
    # Every ellipse pose pitched up about its own x axis by this many degrees (``gsfixer_windows`` only).
    pitch_degrees: list[float] = reads(EVERY, factory=lambda: [0.0], range=each(FINITE))
    ellipse_frames: int = reads(EVERY, default=64, range=at_least(1))
    clip_rule: ClipRule = reads(EVERY, default=ClipRule.reference_pairs)
    # GSFixer's ellipse on its world axes as released, or corrected to the cameras' frame (``gsfixer_windows``
    # only; the embedded ``reference_pairs`` ellipse is its own).
    ellipse_frame: EllipseFrame = reads(EVERY, default=EllipseFrame.gsfixer_world)
    # Each clip's first and last rendered frames replaced by the captured reference images they are rendered at,
    # as GSFixer's restorer sees them (``with_captured_ends``); the paper scale sets it (conf/deploy/paper.yaml).
    captured_ends: bool = reads(EVERY, default=False)

    def validate(self) -> None:
        check_ranges(self)  # the per-round lists: not empty (one value per repair round, cycling)
        if self.clip_rule != ClipRule.gsfixer_windows:
            if any(pitch != 0.0 for pitch in self.pitch_degrees):
                raise ConfigError("pitch_degrees", f"only clip_rule=gsfixer_windows pitches its poses, got "
                                                   f"{list(self.pitch_degrees)} with clip_rule={self.clip_rule}")
            return
        if self.frames_per_clip < 7:
            raise ConfigError("frames_per_clip", f"clip_rule=gsfixer_windows bridges with (frames_per_clip - 1) // 3 "
                                                 f">= 2 poses each side, so at least 7 frames, got {self.frames_per_clip}")
        if self.ellipse_frames < self.frames_per_clip - 2 * ((self.frames_per_clip - 1) // 3):
            raise ConfigError("ellipse_frames", f"clip_rule=gsfixer_windows needs at least one window of "
                                                f"{self.frames_per_clip - 2 * ((self.frames_per_clip - 1) // 3)} "
                                                f"poses, got {self.ellipse_frames}")
