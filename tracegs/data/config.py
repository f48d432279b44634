"""Hyperparameters of scene loading, the synthetic benchmark, paired-clip preparation and the DataModule.

Defaults are the embedded (CPU) scale. Paper-scale values (paper Sec. 4.1, supplement A.2/A.4) are given
in each field's comment; the lead's Hydra yaml sets them for the cluster runs.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from tracegs.modes import Mode
from tracegs.products import BASELINE, DEPLOY, EVALUATE, EVERY, PREPARE, RESTORE, execution, handed_in, reads
from tracegs.ranges import SEED, at_least, each, positive, within
from tracegs.splat.config import GaussianFitConfig, TrajectoryConfig


class Split(Mode):
    """A seed list of the synthetic benchmark (``SyntheticConfig``)."""

    train = "train"
    val = "val"  # the scenes embedded settings are chosen on
    test = "test"  # held out: no stage trains on them
    # Variant A's own scenes: the embedded restorer is pretrained on them, as GSFixer was on scenes of its own before
    # TRACE-GS froze it (supplement, "Pseudo-target generation"). Disjoint from the three lists above.
    pretrain = "pretrain"


class SourcePreset(Mode):
    """A dataset's COLMAP folder layout (tracegs.data.colmap.PRESETS)."""

    synthetic = "synthetic"
    mipnerf360 = "mipnerf360"
    dl3dv = "dl3dv"
    nerfbusters = "nerfbusters"
    custom = "custom"


class ViewRule(Mode):
    """How a scene's K-view sets are picked from its training views where no split file lists them
    (tracegs.data.splits)."""

    nested = "nested"  # spread evenly around the capture and nested, V_3 in V_6 in ... in V_18 (paper Sec. 3)
    linspace = "linspace"  # GSFixer's: each set on its own, np.linspace over the training views, both ends included


class PretrainPairs(Mode):
    """Where the pretraining split's clips run (experiment.baseline_split=pretrain): the pairs variant A learns from."""

    # Along deployment's synthesised trajectories, with the procedural scene's ground truth at every frame.
    trajectory = "trajectory"
    # Through the captured cameras, with the captured images as ground truth: what a real capture offers, and the
    # kind of pairs GSFixer was trained on (renders of a sparse fit at held-out captured views).
    captured = "captured"


class PseudoTarget(Mode):
    """Where a training clip's target comes from (supplement A.4)."""

    gt = "gt"  # the scene's ground truth (synthetic scenes only)
    restorer = "restorer"  # the frozen pretrained restorer on R_d (the paper)
    dense = "dense"  # R_d itself


@dataclass
class SyntheticConfig:
    """The embedded synthetic benchmark: procedural Gaussian scenes rendered along camera paths."""

    root: str = execution(default="data/synthetic")
    # Between them the training scenes show every ground (3) and backdrop (6) texture (tests/data/test_synthetic.py):
    # seeds 0-3 showed 2 grounds and 3 backdrops, and a restorer trained on them lost 3.8 dB against its input
    # on validation scene 50, whose backdrop (hubble deep field) none of them showed. The first six (0, 2, 3,
    # 9, 14, 19) show them all; six more lift the restorers on validation clips (conf/data/synthetic.yaml).
    train_seeds: list[int] = reads(PREPARE, BASELINE, split=Split.train,
                                   factory=lambda: [0, 2, 3, 9, 14, 19, 4, 5, 6, 7, 8, 10], range=each(SEED))
    # Disjoint from train_seeds
    test_seeds: list[int] = reads(PREPARE, DEPLOY, EVALUATE, split=Split.test, factory=lambda: [100, 101],
                                  range=each(SEED, non_empty=False))
    # Scenes of the training distribution that no stage trains on: embedded settings are chosen on their
    # clips (``prepare.split=val``), never on the test scenes. Disjoint from both lists above.
    val_seeds: list[int] = reads(PREPARE, split=Split.val, factory=lambda: [50, 51, 52],
                                 range=each(SEED, non_empty=False))
    # Variant A's pretraining scenes (``prepare.split=pretrain``, read by A where experiment.baseline_split says so):
    # a seed range of their own, disjoint from the three lists above.
    pretrain_seeds: list[int] = reads(PREPARE, BASELINE, split=Split.pretrain,
                                      factory=lambda: list(range(200, 212)), range=each(SEED, non_empty=False))
    # Photographs (scikit-image's) that texture every surface of a pretraining scene, in place of the benchmark's:
    # A's scenes of other statistics, as GSFixer's training scenes are not TRACE-GS's (paper, Sec. 4.1). None: the
    # benchmark's textures, so A's scenes differ from the training scenes by seed only.
    pretrain_textures: list[str] | None = reads(PREPARE, BASELINE, split=Split.pretrain, default=None)
    num_views: int = reads(PREPARE, BASELINE, default=32, range=at_least(1))
    height: int = reads(PREPARE, BASELINE, default=48, range=at_least(1))
    width: int = reads(PREPARE, BASELINE, default=72, range=at_least(1))
    # Narrow enough that 9 views leave gaps 12+ views fill (privileged gap)
    fov_x_deg: float = reads(PREPARE, BASELINE, default=50.0,
                             range=within(0, 180, low_open=True, high_open=True))
    # Camera path per seed, cycled: "orbit" (arc around the objects) or "forward" (forward-facing).
    # Default orbit only: the clip / deployment trajectories are 360-degree ellipses, which leave a
    # forward-facing capture's coverage, so dense fits there are no better than sparse ones (measured).
    path_styles: list[str] = reads(PREPARE, BASELINE, factory=lambda: ["orbit"])
    # An open arc, like a walk-around video; a closed ring would wrap
    orbit_arc_deg: float = reads(PREPARE, BASELINE, default=300.0, range=within(0, 360, low_open=True))
    num_objects: int = reads(PREPARE, BASELINE, default=6, range=at_least(1))
    # Density of surface Gaussians on the textured shapes
    gaussians_per_unit_area: float = reads(PREPARE, BASELINE, default=250.0, range=positive())
    # SfM-like points written to points3D (subsampled Gaussian centres)
    init_points: int = reads(PREPARE, BASELINE, default=1500, range=at_least(1))
    background: list[float] = reads(PREPARE, BASELINE, factory=lambda: [0.0, 0.0, 0.0],
                                    range=each(within(0, 1)))


def split_seeds(cfg: SyntheticConfig, split: str) -> list[int]:
    """The scene seeds of the ``"train"``, ``"val"``, ``"test"`` or ``"pretrain"`` split."""
    split = Split.parse(split, "split")
    return list({Split.train: cfg.train_seeds, Split.val: cfg.val_seeds, Split.test: cfg.test_seeds,
                 Split.pretrain: cfg.pretrain_seeds}[split])


def overlapping_seeds(cfg: SyntheticConfig) -> list[int]:
    """Seeds that appear in more than one split (the splits must be disjoint)."""
    seen = [seed for split in Split for seed in set(split_seeds(cfg, split))]
    return sorted({seed for seed in seen if seen.count(seed) > 1})


@dataclass
class SceneSourceConfig:
    """Where scenes come from: a COLMAP dataset layout (presets) or the synthetic benchmark root."""

    root: str = execution(default="data/synthetic")
    preset: SourcePreset = reads(PREPARE, BASELINE, default=SourcePreset.synthetic)  # fills image_dir / sparse_dir
    # None = every scene directory under root (sorted), or the split's list
    scenes: list[str] | None = reads(PREPARE, BASELINE, default=None)
    # Scene lists (one name a line) for datasets whose training and benchmark scenes share a root (DL3DV):
    # prepare and training read ``train_list``, evaluation ``test_list``; None = every scene under root.
    train_list: str | None = reads(PREPARE, BASELINE, split=Split.train, default=None)
    test_list: str | None = reads(PREPARE, DEPLOY, EVALUATE, split=Split.test, default=None)
    # None = preset default, e.g. "images_4" for Mip-NeRF 360
    image_dir: str | None = reads(PREPARE, BASELINE, default=None)
    sparse_dir: str | None = reads(PREPARE, BASELINE, default=None)  # None = preset default, e.g. "sparse/0"
    # Resize images (and intrinsics) to this size; None = as stored
    height: int | None = reads(PREPARE, BASELINE, default=None, range=at_least(1))
    width: int | None = reads(PREPARE, BASELINE, default=None, range=at_least(1))  # paper scale: 480 x 720
    # Downsize each image (and its intrinsics) so that its longer side is at most this, its aspect ratio kept,
    # instead of to height x width: a capture of portrait and landscape photos keeps both (capture.size).
    long_side: int | None = reads(PREPARE, BASELINE, default=None, range=at_least(1))
    # Centre the cameras and scale them into the unit ball (3DGS convention)
    normalize: bool = reads(PREPARE, BASELINE, default=True)
    test_every: int = reads(PREPARE, BASELINE, default=8, range=at_least(2))
    # Where a scene has no split file for a count. nested: V_s in V_d, which training clips need (paper Sec. 3).
    # linspace: GSFixer's sparse views (datasets/colmap_debug.py l. 416-422), not nested; the evaluation-only
    # datasets use it (conf/data/mipnerf360.yaml, conf/data/nerfbusters.yaml).
    view_rule: ViewRule = reads(PREPARE, BASELINE, default=ViewRule.nested)


@dataclass
class CaptionConfig:
    """Where clip captions come from."""

    # Local BLIP-2 weights (transformers layout); None = the deterministic source
    blip2_path: str | None = reads(EVERY, default=None)
    # Deterministic source: used when a scene has no caption.txt
    fallback: str = reads(EVERY, default="a photo of a scene")
    # unstated by the paper: BLIP-2 caption length
    max_new_tokens: int = reads(EVERY, default=30, range=at_least(1))



@dataclass
class PrepareConfig:
    """Paired-clip preparation (paper Sec. 4.1 "Training Data", supplement A.2 / A.4)."""

    cache_dir: str = execution(default="data/cache")
    # Which scenes to prepare. "test" builds a held-out cache that no stage trains on; evaluation scores
    # restorers on its clips (``evaluation.held_out_cache``): the synthetic test seeds, or a real dataset's test
    # scenes with clips through captured cameras between consecutive sparse views, whose ground truth is the
    # capture (paper silent; tracegs/data/held_out.py says why). "val" (synthetic only) builds the validation
    # cache that embedded settings are chosen on.
    # Training reads the train split's cache whatever split a prepare builds.
    split: Split = reads(PREPARE, default=Split.train)
    # Fitted snapshots (PLY) per (scene, view set): resumable unit
    work_dir: str = execution(default="data/prepare_work")
    student_views: list[int] = reads(PREPARE, BASELINE, factory=lambda: [3, 6, 9], range=each(at_least(1)))
    # None = all training views. Empty: no R_d (a held-out cache that scores restorers from R_s against ground
    # truth, pseudo_target 'gt'; the privileged report needs the teacher's R_d).
    dense_views: list[int | None] = reads(PREPARE, BASELINE, factory=lambda: [12, 18, None],
                                          range=each(at_least(1), non_empty=False))
    # Also fit the smallest student set to the final iteration, whose snapshot is the non-privileged teacher of
    # variant B for every K. False stops each sparse fit at its last student snapshot: the student conditions
    # are the same bytes, and a sparse fit costs 17k instead of 30k iterations.
    student_final_fits: bool = reads(PREPARE, BASELINE, default=True)
    # paper: 7000, 17000
    student_snapshots: list[int] = reads(PREPARE, BASELINE, factory=lambda: [140, 340],
                                         range=each(at_least(1)))
    # Embedded: 600 iterations, snapshots 140/340/600 (paper 7k/17k/30k x 0.02).
    fit: GaussianFitConfig = reads(PREPARE, BASELINE, factory=GaussianFitConfig)
    # Processes for fits and clip renders (one thread each); 1 = in-process. Paper: 1 per GPU
    workers: int = execution(default=2, range=at_least(1))
    # Each clip belongs to one student view count K (clips divided evenly among student_views; the paper is silent)
    # and holds every student snapshot of it (one paired clip per snapshot).
    # Paper: 75 (a real dataset's held-out split: one clip per reference pair of each K)
    clips_per_scene: int = reads(PREPARE, BASELINE, default=8, range=at_least(1))
    # True: each trajectory, drawn on the smallest K's views, serves every K (nested view sets, V_3 in V_6 in V_9) and
    # is restored into one pseudo-target; clips_per_scene counts trajectories x K. False: each clip has its own
    # trajectory on its own K's views and its own pseudo-target. Paper: "150 paired clips" per scene, read as 25
    # trajectories x 3 K x 2 snapshots with one pseudo-target each (2,800 restorations for 112 scenes, not 16,800).
    shared_trajectories: bool = reads(PREPARE, BASELINE, default=False)
    frames_per_clip: int = reads(PREPARE, BASELINE, default=9, range=at_least(1))  # paper: 49
    # A real dataset's held-out clip whose two reference views have fewer captured images between them than
    # frames_per_clip - 2: False refuses the scene; True repeats captured frames evenly to fill the clip (each
    # frame keeps its own ground truth). Paper silent; Mip-NeRF 360 captures hold 125-311 images, fewer than 47
    # per gap at K = 6 and 9, and 49 is the frame count GSFixer's learned positional embeddings were trained at.
    # Training reads latents only: how held-out clips are filled (and, below, whether a cache keeps frames for
    # inspection) leaves the trained restorers as they are.
    held_out_repeat_frames: bool = reads(PREPARE, default=False)
    # Clips follow the deployment trajectories: the Hydra configs set this to ``${deploy.trajectory}``.
    trajectory: TrajectoryConfig = reads(PREPARE, BASELINE, factory=TrajectoryConfig)
    # The train split's targets (paper: restorer, the frozen GSFixer); a procedural benchmark's other splits (val,
    # test, pretrain) are scored against, or pretrain A on, their ground truth whatever this says (``clip_target``).
    pseudo_target: PseudoTarget = reads(PREPARE, BASELINE, default=PseudoTarget.gt)
    # The pseudo-target generator's transformer (pseudo_target=restorer): None = the backbone's own pretrained
    # weights (paper scale: GSFixer's released transformer, variant A); the embedded scale sets it to variant A's
    # product (``${artifacts.baseline_weights}``, located by its identity), which the train split's cache then
    # reads as its own settings (tracegs.config.identity); a folder given by path is known by its content.
    pseudo_target_weights: str | None = handed_in(PREPARE, default=None)
    # The pretraining split's clips (experiment.baseline_split=pretrain): see PretrainPairs; and how many per scene
    # along trajectories (None: clips_per_scene). Captured-camera clips are every reference pair of every K.
    pretrain_pairs: PretrainPairs = reads(PREPARE, BASELINE, split=Split.pretrain, default=PretrainPairs.trajectory)
    pretrain_clips_per_scene: int | None = reads(PREPARE, BASELINE, split=Split.pretrain, default=None,
                                                 range=at_least(1))
    # The view counts of the pretraining split's sparse fits (None: student_views). A pretrained restorer makes the
    # pseudo-targets from R_d, so its pairs must reach inputs as good as R_d: a restorer that never saw a near-clean
    # rendering repaints it (measured: A from R_d 5 dB below R_d itself with pairs at 3, 6 and 9 views only).
    pretrain_views: list[int] | None = reads(PREPARE, BASELINE, split=Split.pretrain, default=None,
                                             range=each(at_least(1)))
    # Classifier-free guidance of the restorer making pseudo-targets (pseudo_target=restorer), its own setting so
    # that a deployment guidance change keeps the cache. Paper silent; 6 is GSFixer's inference default.
    pseudo_target_guidance: float = reads(PREPARE, BASELINE, default=6.0, range=at_least(0))
    # How far from the noise end the pseudo-target's sampling starts (pseudo_target=restorer): 1 samples from pure
    # noise conditioned on R_d (GSFixer's release: its video-to-video pipeline's prepare_latents draws pure noise
    # and its strength-based get_timesteps is never called; the paper is silent); below 1 starts from R_d's own
    # latent noised to that point of the schedule (SDEdit, ``sampler.partial_start``), so the target keeps what
    # R_d already has right and the restorer repaints only what the noise covers.
    pseudo_target_strength: float = reads(PREPARE, BASELINE, default=1.0, range=within(0.0, 1.0, low_open=True))
    # Clip captions (the Hydra configs set every field to deploy.captions'): see tracegs/data/captions.py.
    captions: CaptionConfig = reads(PREPARE, BASELINE, factory=CaptionConfig)
    shard_index: int = execution(default=0, range=at_least(0))
    # shard by scene for Hydra multirun / SLURM arrays
    num_shards: int = execution(default=1, range=at_least(1))
    force: bool = execution(default=False)
    contact_sheet: bool = execution(default=True)
    # uint8 frames of every condition, the target, references and ground truth in the shards. None = only in a
    # held-out split's cache (val / test), which evaluation scores in pixels; training reads latents only.
    store_frames: bool | None = reads(PREPARE, default=None)
    latent_dtype: str = reads(PREPARE, BASELINE, default="float16")
    seed: int = reads(PREPARE, BASELINE, default=0, range=SEED)


@dataclass
class DataModuleConfig:
    """Which cached conditions the PairedClipDataModule serves and how it batches them."""

    # Handed in, a cache is known by its manifest (tracegs.data.cache_keys.MANIFEST, which cannot be imported
    # here), which records every stored tensor's checksum: hashing the tensors would read the whole cache.
    cache_dir: str = handed_in(BASELINE, content=("manifest.json",), default="data/cache")
    # the clips of these K are served
    student_views: list[int] = reads(BASELINE, factory=lambda: [3, 6, 9], range=each(at_least(1)))
    student_snapshots: list[int] = reads(BASELINE, factory=lambda: [140, 340], range=each(at_least(1)))
    batch_size: int = reads(BASELINE, default=2, range=at_least(1))  # paper: 2 per GPU
    # Serve only the first n clips of each scene (None: every clip the cache holds), so that stages of one
    # experiment can read different amounts of one cache (experiment.baseline_clips_per_scene).
    clips_per_scene: int | None = reads(BASELINE, default=None, range=at_least(1))
    num_workers: int = execution(default=0, range=at_least(0))
    val_scenes: list[str] = reads(BASELINE, factory=list)  # scene names held out for validation
    # supplement A.2: zero text embedding, shared by both roles
    caption_dropout: float = reads(BASELINE, default=0.1, range=within(0, 1, high_open=True))
    seed: int = reads(BASELINE, default=0, range=SEED)


class Matcher(Mode):
    """Which image pairs structure-from-motion matches (COLMAP's matchers)."""

    auto = "auto"  # sequential for a video's frames, exhaustive for photos
    exhaustive = "exhaustive"  # every pair: photos in any order (quadratic in their number)
    sequential = "sequential"  # each image with the next ones in name order: frames of a video


@dataclass
class SfmConfig:
    """Structure-from-motion with pycolmap for a capture without a COLMAP model (tracegs.data.sfm). The
    reconstruction is keyed by its photos and the settings it reads; the restoration of the capture reads them too."""

    # Reconstructions are kept here, one folder per (photos, settings below): a rerun reuses it.
    dir: str = execution(default="data/captures")
    matcher: Matcher = reads(RESTORE, default=Matcher.auto)
    # images after each one a sequential matcher pairs it with
    sequential_overlap: int = reads(RESTORE, default=10, range=at_least(1))
    # longest side structure-from-motion sees: a larger photo is downsized to it once, before SIFT, so memory is
    # bounded by this size, not the photos'
    max_image_size: int = reads(RESTORE, default=1600, range=at_least(1))
    # longest side of the scene's undistorted images (aspect kept), what the fit and the scores can use at most:
    # the paper's frames are 720 wide
    scene_size: int = reads(RESTORE, default=720, range=at_least(1))
    max_features: int = reads(RESTORE, default=8192, range=at_least(1))  # SIFT features per image
    # The lens model fitted, then undone: the images the scene is made of are undistorted to PINHOLE.
    camera_model: str = reads(RESTORE, default="SIMPLE_RADIAL")
    # registered images a disconnected model needs to be reported (COLMAP: 10)
    min_model_size: int = reads(RESTORE, default=3, range=at_least(1))
    threads: int = execution(default=-1, range=at_least(1, -1))  # -1: every core
    seed: int = reads(RESTORE, default=0, range=SEED)  # RANSAC and mapping draws


def is_procedural(source: SceneSourceConfig | Any) -> bool:
    """Whether ``data.source`` is the procedural benchmark (a typed or composed config node)."""
    return source.preset == SourcePreset.synthetic


def clip_target(split: str, pseudo_target: str, procedural: bool) -> PseudoTarget:
    """The target of the clips a preparation of ``split`` makes: the configured ``pseudo_target`` for the train split
    (and for any split of a real dataset, whose held-out clips set theirs); the ground truth for the other splits of
    a procedural benchmark, which is what they are scored against (val, test) or what A is pretrained on
    (pretrain: a restorer trained elsewhere, with ground truth, as GSFixer was)."""
    if procedural and Split.parse(split, "data.prepare.split") != Split.train:
        return PseudoTarget.gt
    return PseudoTarget.parse(pseudo_target, "data.prepare.pseudo_target")


def as_prepared(cfg: PrepareConfig, procedural: bool) -> PrepareConfig:
    """``cfg`` as a preparation of its split makes it: the split's target (``clip_target``); the pretraining split
    of a procedural benchmark fits no teacher (A reads R_s and the ground truth only), and its captured-camera clips
    repeat captured frames where a gap between reference views is short (GSFixer's pairs are captured frames)."""
    target = clip_target(cfg.split, cfg.pseudo_target, procedural)
    if not (procedural and cfg.split == Split.pretrain):
        return dataclasses.replace(cfg, pseudo_target=target)
    return dataclasses.replace(cfg, pseudo_target=target, dense_views=[], student_final_fits=False,
                               held_out_repeat_frames=cfg.pretrain_pairs == PretrainPairs.captured,
                               clips_per_scene=cfg.pretrain_clips_per_scene or cfg.clips_per_scene,
                               student_views=list(cfg.pretrain_views or cfg.student_views))


def with_variant_teacher(dense_views: list[int | None], teacher_views: int | None,
                         student_views: list[int]) -> list[int | None]:
    """``dense_views`` and the dense teacher of the variant a command runs for (``teacher.views``; None: all training
    views), so a Table 3 variant brings the teacher condition it reads: preparing for a variant with a 12-view
    teacher fits that teacher without naming it. A teacher seeing as many views as a student is a sparse fit's final
    snapshot instead (``fits_variant_teacher``); a count between the student sets is no teacher a cache can hold,
    and is left for validation to refuse. Counts ascending, all views last, as the fits are listed."""
    privileged = teacher_views is None or not student_views or teacher_views > max(student_views)
    views = set(dense_views) | ({teacher_views} if privileged else set())
    return sorted(views - {None}) + ([None] if None in views else [])


def fits_variant_teacher(student_final_fits: bool, teacher_views: int | None, student_views: list[int]) -> bool:
    """``student_final_fits``, or the variant's teacher is the smallest sparse set fitted to its final snapshot
    (the non-privileged teacher of Table 3)."""
    return bool(student_final_fits) or (bool(student_views) and teacher_views == min(student_views))
