"""Hyperparameters of deployment (supplement A.5) and evaluation (supplement B). Embedded-scale defaults.

Paper scale: ``total_iters=30000``, ``repair_iters=[7000, 17000, 27000]``, ``lambda_reg=1``,
``trajectory.frames_per_clip=49``, ``max_clips_per_round=None``, ``clip_batch=1``; the restorer runs its full
M = 50-step schedule (``backbone.schedule.deploy_steps``) with the backbone's guidance scale, so neither is
repeated here.
"""

from __future__ import annotations

from dataclasses import dataclass

from tracegs.data.config import CaptionConfig, SfmConfig, ViewRule
from tracegs.errors import ConfigError
from tracegs.modes import Mode
from tracegs.products import DEPLOYMENT, RESTORE, execution, reads
from tracegs.ranges import SEED, at_least, check_ranges, each, within
from tracegs.splat.config import TrajectoryConfig

METHODS = ("3dgs", "baseline", "tracegs")
# A count K of captured views deployment starts from (Algorithm 1: its clips run between two of them).
CAPTURED_VIEWS = at_least(2, why="deployment's clips run between two captured reference views")


class Protocol(Mode):
    """Which GSFixer-protocol values a configuration takes: the paper scale's YAML derives each protocol field
    from it with ``${tracegs.protocol:<release value>,<corrected value>}`` (docs/cluster.md lists them)."""

    gsfixer_release = "gsfixer_release"  # GSFixer's release as it runs (variant A is GSFixer: Table 1's row)
    corrected = "corrected"  # each deviation of the release from its paper corrected, a named field apiece
    own = "own"  # every field as its YAML sets it (the embedded scale's measured defaults)


class KeptFrames(Mode):
    """Which restored frames of a clip become pseudo views (Eq. supp-round-pseudo-set)."""

    # GSFixer's release (gsfixer/extrapolation/outpaint/base.py l. 129-140): all of them, the two at the
    # captured views included (49 a window, 343 a round of 7 windows).
    every = "every"
    # Corrected: the frames between the clip's ends, whose cameras are captured views that L_sparse supervises.
    between_ends = "between_ends"


class Resolution(Mode):
    """The image size deployment fits, refines and scores at (tracegs.deploy.scenes.deployment_source)."""

    # GSFixer's release: the dataset's own downsampled images (``data_factor = 4``: images_4, arguments/__init__.py
    # l. 64, datasets/colmap_debug.py l. 160-170), data.source's size ignored; each clip is resized bilinearly to
    # the restorer's frame (``clip_size``: gsfixer/extrapolation/outpaint/base.py l. 63, the captured ends
    # sparse.py l. 287-296), its restored frames stay at that size and each pseudo view's render is resized
    # bilinearly to them (train.py l. 204-208).
    dataset = "dataset"
    # Corrected: every image resized (Lanczos) to data.source's height x width on load, and fitted, restored and
    # scored at that one size.
    frame = "frame"


class Upscale(Mode):
    """How a clip larger than the restorer's frames is restored (tracegs.deploy.tiles; docs/your_capture.md
    measures both)."""

    # Overlapping tiles of the restorer's frame size, each restored, blended with linear feathering: every pixel
    # is restored at its own resolution.
    tiles = "tiles"
    # The clip resized to the restorer's frame and restored, its correction (restored - input) upsampled and
    # added to the rendering: the rendering's finer detail kept, one restoration per clip.
    residual = "residual"


@dataclass
class RefinementConfig:
    """The restore-refine loop (Algorithm 1 bottom, Eq. supp-refinement-objective, Eq. supp-pseudo-weight)."""

    total_iters: int = reads(DEPLOYMENT, default=600, range=at_least(1))  # J; paper 30000
    # paper 7000/17000/27000
    repair_iters: list[int] = reads(DEPLOYMENT, factory=lambda: [140, 340, 540], range=each(at_least(1)))
    lambda_reg: float = reads(DEPLOYMENT, default=1.0, range=at_least(0))  # peak of the half-sine w_reg
    trajectory: TrajectoryConfig = reads(DEPLOYMENT, factory=TrajectoryConfig)
    captions: CaptionConfig = reads(DEPLOYMENT, factory=CaptionConfig)  # the training clips' caption rule
    # Clips restored per round: None = every clip of the round's rule (one per reference pair of the chained
    # captured views, or every GSFixer window: the paper's protocol); n = a random n of them per round (the
    # embedded default samples 2 to keep CPU deployment within minutes).
    max_clips_per_round: int | None = reads(DEPLOYMENT, default=2, range=at_least(1))
    # clips restored per sampler call (memory knob only; paper scale: 1)
    clip_batch: int = reads(DEPLOYMENT, default=4, range=at_least(1))
    # Reverse steps per restoration; None = the backbone's full M-step schedule (the paper's protocol).
    steps: int | None = reads(DEPLOYMENT, default=None, range=at_least(1))
    seed: int = reads(DEPLOYMENT, default=0, range=SEED)
    protocol: Protocol = reads(DEPLOYMENT, default=Protocol.own)
    kept_frames: KeptFrames = reads(DEPLOYMENT, default=KeptFrames.between_ends)  # embedded: as corrected
    resolution: Resolution = reads(DEPLOYMENT, default=Resolution.frame)  # embedded: as corrected
    # [height, width] each clip's frames and reference images are resized to (bilinearly) before the restorer sees
    # them, where they differ (``resolution=dataset``); None = as rendered.
    clip_size: list[int] | None = reads(DEPLOYMENT, default=None, range=each(at_least(1)))
    # [height, width] of the frames the restorer works on, where the fitted views are larger (a capture fitted at
    # capture.size): each clip is rendered at this aspect ratio with the captured views' longer side and restored
    # by ``upscale`` at this size; None = clips restored as rendered (the benchmarks: the views are its frames).
    restorer_frame: list[int] | None = reads(DEPLOYMENT, default=None, range=each(at_least(1)))
    upscale: Upscale = reads(DEPLOYMENT, default=Upscale.tiles)
    # share of a tile's side its neighbour overlaps (``upscale=tiles``): the width of the feathered seams
    tile_overlap: float = reads(DEPLOYMENT, default=0.25, range=within(0, 0.9))
    # The sparse-view rule of the scenes deployment fits and scores, where no split file lists a K-view set; None =
    # data.source.view_rule. GSFixer's release picks DL3DV's as every other dataset's (its one loader,
    # datasets/colmap_debug.py l. 402-422: np.linspace over the every-8th split's training views), where the DL3DV
    # config's own rule is nested for its training clips (paper Sec. 3).
    view_rule: ViewRule | None = reads(DEPLOYMENT, default=None)

    def validate(self) -> None:
        check_ranges(self)  # repair_iters: not empty, each >= 1
        repairs = list(self.repair_iters)
        if any(b <= a for a, b in zip(repairs, repairs[1:])):
            raise ConfigError("repair_iters", f"must be strictly increasing, got {repairs}")
        if repairs[-1] >= self.total_iters:
            raise ConfigError("repair_iters", f"{repairs} must lie strictly inside (0, total_iters={self.total_iters})")
        if self.resolution == Resolution.dataset and self.clip_size is None:
            raise ConfigError("clip_size", "resolution=dataset fits at the dataset's own image size, so the "
                                           "restorer's clips need a size: set [height, width]")
        for name in ("clip_size", "restorer_frame"):
            size = getattr(self, name)
            if size is not None and len(size) != 2:
                raise ConfigError(name, f"must be [height, width] or null, got {list(size)}")
        if self.clip_size is not None and self.restorer_frame is not None:
            raise ConfigError("restorer_frame", "clip_size already resizes every clip to the restorer's frames: "
                                                "set one of them")
        try:
            self.trajectory.validate()
        except ConfigError as error:
            raise error.under("trajectory") from error


@dataclass
class EvaluationConfig:
    """Which scenes, view counts and methods to deploy, and what to write (supplement B)."""

    out_dir: str = execution(default="outputs/eval")
    # Which (scene, views, method) units to compute (methods, views, scenes) and which extra files to write
    # (save_*, grid_views, video_*): each unit is its own file, recorded with its own settings, so selections of
    # units share one evaluation folder and merge into one results.json.
    methods: list[str] = execution(factory=lambda: list(METHODS))
    views: list[int] = execution(factory=lambda: [3, 6, 9], range=each(CAPTURED_VIEWS))
    scenes: list[str] | None = execution(default=None)  # None = the benchmark's test scenes
    # A paired-clip cache of held-out scenes with ground truth (``tracegs-prepare data.prepare.split=test``).
    # When set, each diffusion restorer also restores its clips and is scored against its input R_s.
    held_out_cache: str | None = execution(default=None)
    # Sharding (Hydra multirun / SLURM array): this job evaluates every num_shards-th (scene, views) unit.
    shard_index: int = execution(default=0, range=at_least(0))
    num_shards: int = execution(default=1, range=at_least(1))
    # Units evaluated in parallel by forked CPU processes (1 intra-op thread each); GPU runs use 1.
    workers: int = execution(default=2, range=at_least(1))
    lpips: bool = reads(DEPLOYMENT, default=True)
    # "3dgs" (official 3DGS metrics) or "standard"; see eval/metrics.py
    lpips_convention: str = reads(DEPLOYMENT, default="3dgs")
    # The headline SSIM column's convention, "torchmetrics" (float images) or "gsfixer" (8-bit PNGs, GSFixer's
    # metrics.py l. 25-35 and 74); the other one fills the second SSIM column (see eval/metrics.py).
    ssim_convention: str = reads(DEPLOYMENT, default="torchmetrics")
    # torchvision's VGG16 ImageNet weights (vgg16-397923af.pth) for LPIPS; None = the torch hub cache's copy.
    lpips_weights: str | None = reads(DEPLOYMENT, default=None)
    # Stop before any work when LPIPS cannot be computed (the paper's tables report it); else "n/a" in tables.
    require_lpips: bool = reads(DEPLOYMENT, default=False)
    # Fig. 6 curves of the diffusion restorers where per-frame GT exists
    per_step: bool = reads(DEPLOYMENT, default=True)
    save_media: bool = execution(default=True)  # qualitative grid PNG + comparison video per scene/view count
    # Each method's refined 3DGS as PLY (models/<scene>/views_<K>_<method>.ply)
    save_models: bool = execution(default=False)
    save_frames: bool = execution(default=False)  # each method's renders along the video's trajectory as PNG frames
    grid_views: int = execution(default=3, range=at_least(1))  # test views shown in the qualitative grid
    # frames of the comparison video along a test trajectory
    video_frames: int = execution(default=24, range=at_least(1))
    video_fps: int = execution(default=8, range=at_least(1))
    force: bool = execution(default=False)  # recompute finished units even when their settings are unchanged
    variant: str | None = execution(default=None)  # ablation variant name recorded in results.json (Table 3)
    progress: bool = execution(default=True)


@dataclass
class CaptureConfig:
    """A capture of your own for ``tracegs-restore``: a COLMAP scene folder, a folder of photos or a video."""

    # A COLMAP scene folder (<path>/images/ and <path>/sparse/0, undistorted: image_undistorter's layout), or a
    # folder of photos (in it or in its images/) that structure-from-motion reconstructs first.
    path: str | None = reads(RESTORE, default=None)
    video: str | None = reads(RESTORE, default=None)  # a video file instead: frames sampled, then reconstructed
    # frames taken from the video: the sharpest of each of this many windows
    frames: int = reads(RESTORE, default=60, range=at_least(1))
    # K captured views the 3DGS is fitted from (the view-selection rule)
    views: int = reads(RESTORE, default=6, range=CAPTURED_VIEWS)
    # Longer side, in pixels, each view is fitted, restored and scored at (at most: smaller images are not
    # enlarged), its aspect ratio kept, so portrait views stay portrait: data.source.long_side; the photos'
    # undistorted images are kept at it (capture.sfm.scene_size).
    size: int = reads(RESTORE, default=360, range=at_least(1))
    sfm: SfmConfig = reads(RESTORE, factory=SfmConfig)
