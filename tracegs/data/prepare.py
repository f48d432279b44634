"""Paired-clip preparation (paper Sec. 4.1 "Training Data"; supplement A.2 and A.4).

For every scene and view set V_b (sparse K = 3, 6, 9 and dense 12, 18, all) a 3DGS is fitted with
snapshots; the student condition R_s comes from the early snapshots (paper 7k / 17k) of the sparse fits,
the teacher condition R_d from the final snapshot (paper 30k). Each clip belongs to one student view count K
(the scene's clips divided evenly among K, ``clip_view_counts``) and follows deployment's rule for K captured
views: its trajectory P is a round of ``round_clips`` on the K-view set, starting and ending at two of its
views. Along P it renders that K's student snapshots, the teacher conditions (dense sets, and the smallest
sparse set's final snapshot: variant B's teacher) and the pseudo-target, which comes from ground truth, the
dense rendering, or a frozen restorer applied to R_d (the paper's choice). Frozen encoders run once here: the
cache holds codec latents, reference tokens and text embeddings (layout: ``cache_keys``), so training never
loads them.

Work units and resumability: one PLY per (scene, view set, snapshot) in ``work_dir`` and one safetensors
shard per (scene, clip) in ``cache_dir``, written after the scene files it indexes; every file is written
atomically, finished units are skipped, and ``force`` redoes them. Runs can be sharded by scene
(``shard_index`` / ``num_shards``); each shard writes its own manifest, and the last to finish joins them all
into the cache's manifest (``merge_manifests``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from rich.progress import Progress
from safetensors import SafetensorError, safe_open
from torchmetrics.functional.image import peak_signal_noise_ratio

from tracegs.console import PlainProgress
from tracegs.data import cache_keys
from tracegs.data.cache_keys import CACHE_VERSION, MANIFEST, condition_key
from tracegs.data.captions import clip_caption, require_captioner
from tracegs.data.colmap import Scene, SceneFormatError, list_scenes, load_scene
from tracegs.data.config import (
    PrepareConfig,
    PretrainPairs,
    SceneSourceConfig,
    Split,
    SyntheticConfig,
    as_prepared,
)
from tracegs.data.datamodule import CacheError, clip_record, repeats_frames
from tracegs.data.held_out import captured_clips
from tracegs.data.images import to_uint8
from tracegs.data.sources import is_procedural
from tracegs.data.splits import SceneSplit, require_sparse_in_dense, split_scene, view_set_key
from tracegs.data.synthetic import (
    GT_PLY,
    benchmark_scene_names,
    generate_benchmark,
    ground_truth_model,
    render_images,
    scene_background,
)
from tracegs.errors import InputFileError, require_writable_dir
from tracegs.io import (
    atomic_write,
    checksum_problem,
    non_finite_keys,
    read_safetensors,
    save_safetensors_atomic,
    write_json_atomic,
)
from tracegs.processes import WorkerPool, run_units
from tracegs.products import Product, read_values
from tracegs.restorer.build import Backbone
from tracegs.restorer.config import sections_not_in_cache
from tracegs.splat.cameras import Camera
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.fit import View, fit_gaussians
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.ply import load_ply, save_ply
from tracegs.splat.render import render_clip, require_available
from tracegs.splat.trajectory import round_clips, with_captured_ends

log = logging.getLogger(__name__)

MIN_INIT_POINTS = 64  # fewer triangulated points than this: initialise the fit randomly instead


class PrepareError(ValueError):
    """The preparation configuration or input data cannot be used."""


@dataclass
class ScenePlan:
    """A validated scene: its data, split and the fits it needs (view-set key -> snapshot iterations); for a
    captured scene's held-out split, its clips through captured cameras (``data.held_out``)."""

    scene: Scene
    split: SceneSplit
    fits: dict[str, list[int]]
    captured: list[dict] | None = None


def captures_held_out(source: SceneSourceConfig, cfg: PrepareConfig) -> bool:
    """Whether a scene's clips run through its captured cameras (the held-out split of a real dataset, whose only
    ground truth is the capture, or the pretraining split with ``pretrain_pairs=captured``) rather than along
    deployment's synthesised trajectory."""
    if cfg.split == Split.pretrain:
        return cfg.pretrain_pairs == PretrainPairs.captured
    return cfg.split == Split.test and not is_procedural(source)


def _view_counts(cfg: PrepareConfig) -> list[int | None]:
    return list(cfg.student_views) + list(cfg.dense_views)


def teacher_view_counts(cfg: PrepareConfig) -> list[int | None]:
    """View sets fitted to their final snapshot, so usable as a teacher condition ``d{V}``: the dense sets and,
    with ``student_final_fits``, the smallest sparse set (variant B's teacher for every student K, Table 3)."""
    return ([min(cfg.student_views)] if cfg.student_final_fits else []) + list(cfg.dense_views)


def plan_scene(source: SceneSourceConfig, cfg: PrepareConfig, name: str) -> ScenePlan:
    """Load and split a scene, and list the fits; raises before anything is written on bad input."""
    scene = load_scene(source, name)
    split = split_scene(scene, source, _view_counts(cfg))
    if cfg.split == Split.train:  # a held-out cache is scored as evaluation scores: on the benchmark's own sets
        require_sparse_in_dense(split, cfg.student_views, cfg.dense_views, scene.root, source.view_rule)
    finals = teacher_view_counts(cfg)
    fits: dict[str, list[int]] = {}
    for count in _view_counts(cfg):
        snapshots = set(fits.get(view_set_key(count), []))
        if count in finals:
            snapshots.add(cfg.fit.iterations)
        if count in cfg.student_views:
            snapshots |= set(cfg.student_snapshots)
        fits[view_set_key(count)] = sorted(snapshots)
    captured = (captured_clips(scene, split, list(cfg.student_views), cfg.frames_per_clip, cfg.held_out_repeat_frames)
                if captures_held_out(source, cfg) else None)
    if cfg.shared_trajectories and captured is None:
        smallest = min(cfg.student_views)
        for count in cfg.student_views:
            outside = sorted(set(split.views(smallest)) - set(split.views(count)))
            if outside:
                raise PrepareError(f"{scene.root}: views {outside[:5]} of the {smallest}-view set are not in the "
                                   f"{count}-view set, and data.prepare.shared_trajectories gives each trajectory "
                                   f"drawn on the {smallest} views to every K: use nested view sets "
                                   "(data.source.view_rule=nested) or set it to false")
    if cfg.pseudo_target == "gt" and captured is None and not (scene.root / GT_PLY).is_file():
        raise PrepareError(f"{scene.root / GT_PLY}: prepare.pseudo_target='gt' needs a ground-truth scene "
                           "(synthetic scenes, or a real dataset's held-out split); use 'restorer' or 'dense'")
    return ScenePlan(scene, split, fits, captured)


def require_inputs(cfg: PrepareConfig) -> None:
    """What preparation needs from this machine and disk: the rasterizer and the captioner.
    The settings' own rules are checked once, on the composed config (tracegs.config.validate)."""
    require_available(cfg.fit.backend, "data.prepare.fit.backend")
    require_captioner(cfg.captions, "data.prepare.captions")


def shard_scenes(names: list[str], shard_index: int, num_shards: int) -> list[str]:
    """The scenes of one shard: every ``num_shards``-th scene starting at ``shard_index``."""
    return names[shard_index::num_shards]


def scene_seed(seed: int, name: str) -> int:
    """A stable per-scene seed (Python's ``hash`` is salted per process, so use a digest)."""
    return int.from_bytes(hashlib.sha256(f"{seed}:{name}".encode()).digest()[:4], "little")


def settings_digest(settings: object) -> str:
    """Short digest of the settings a work unit depends on: changed settings mean a different unit."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:10]


def fit_unit_paths(work_dir: Path, scene: str, key: str, snapshots: list[int], fit: GaussianFitConfig
                   ) -> dict[int, Path]:
    """PLY per snapshot of one (scene, view set) fit, in a directory named by the fit settings."""
    unit = work_dir / scene / f"fit_{key}_{settings_digest(asdict(fit))}"
    return {it: unit / f"it{it:06d}.ply" for it in snapshots}


def clip_settings(cfg: PrepareConfig, backbone: Backbone) -> str:
    """Digest of everything a clip shard depends on besides the scene (stored in the shard's metadata): the
    fields a cache reads (tracegs.products), less the backbone sections its pseudo-targets do not need."""
    made_with = read_values(backbone.cfg, Product.prepare)
    for section in sections_not_in_cache(cfg.pseudo_target):
        made_with.pop(section)
    return settings_digest({"prepare": read_values(cfg, Product.prepare), "backbone": made_with})


def fit_done(plan: ScenePlan, key: str, cfg: PrepareConfig) -> bool:
    paths = fit_unit_paths(Path(cfg.work_dir), plan.scene.name, key, plan.fits[key], cfg.fit)
    return all(p.is_file() for p in paths.values())


def fit_view_set(plan: ScenePlan, key: str, cfg: PrepareConfig) -> None:
    """Fit 3DGS to one view set and save its snapshots as PLY (one resumable work unit)."""
    paths = fit_unit_paths(Path(cfg.work_dir), plan.scene.name, key, plan.fits[key], cfg.fit)
    scene = plan.scene
    indices = plan.split.view_sets[key]
    views = [View(image=scene.load_image(i), camera=scene.cameras[i]) for i in indices]
    # Initialise from the SfM points the view set sees (data.prepare.fit.init_min_views of its views); too few
    # -> random (3DGS fallback).
    points, colors = scene.points_seen_by(indices, cfg.fit.init_min_views)
    init = GaussianModel.from_points(points, colors) if len(points) >= MIN_INIT_POINTS else None
    snapshots = fit_gaussians(views, cfg.fit, init, plan.fits[key], progress=False)
    for iteration, path in paths.items():
        with atomic_write(path) as tmp:
            save_ply(snapshots[iteration], tmp)


def clip_view_counts(cfg: PrepareConfig, scene: str) -> list[int]:
    """The student view count K of each clip of a scene: the clips divided evenly among ``student_views``, in
    an order seeded by the scene (which K gets one clip more differs between scenes); with
    ``shared_trajectories``, every K in turn for each trajectory."""
    if cfg.shared_trajectories:
        return [views for _ in range(trajectory_count(cfg)) for views in cfg.student_views]
    generator = torch.Generator().manual_seed(scene_seed(cfg.seed, f"{scene}/views"))
    order = [cfg.student_views[i] for i in torch.randperm(len(cfg.student_views), generator=generator).tolist()]
    return [order[c % len(order)] for c in range(cfg.clips_per_scene)]


def trajectory_count(cfg: PrepareConfig) -> int:
    """Distinct trajectories of a scene's clips, each restored into one pseudo-target: one per clip, or one per
    ``len(student_views)`` clips with ``shared_trajectories``."""
    return cfg.clips_per_scene // len(cfg.student_views) if cfg.shared_trajectories else cfg.clips_per_scene


def trajectory_seed(cfg: PrepareConfig, scene: str, views: int) -> int:
    """The seed of the generator that draws the trajectory rounds of a scene's K-view clips."""
    return scene_seed(cfg.seed, f"{scene}/K{views}")


def clip_cameras(plan: ScenePlan, cfg: PrepareConfig) -> list[dict]:
    """Clip trajectories by deployment's rule: a K-view clip is a clip of ``round_clips`` (with ``cfg.trajectory``,
    the deployment's trajectory config) on the K-view set, exactly as deployment from those K captured views
    makes it (every reference pair per round, as the paper scale deploys), rounds 0, 1, ... drawn from one
    generator per (scene, K) until that K has its share of the clips (``clip_view_counts``). A captured scene's
    held-out clips are its planned clips through captured cameras instead (every reference pair of every K).
    With ``shared_trajectories`` the trajectories are drawn on the smallest K's views and each serves every K
    (its clips consecutive). Each clip names its ``trajectory``: clips of one trajectory share a pseudo-target."""
    if plan.captured is not None:
        return plan.captured
    scene = plan.scene
    counts = clip_view_counts(cfg, scene.name)

    def trajectories(views: int, count: int) -> list[dict]:
        indices = plan.split.views(views)
        references = [scene.cameras[i] for i in indices]
        generator = torch.Generator().manual_seed(trajectory_seed(cfg, scene.name, views))
        drawn: list[dict] = []
        round_index = 0
        while len(drawn) < count:
            drawn += [{"refs": [indices[a], indices[b]], "cameras": cameras}
                      for (a, b), cameras in round_clips(references, round_index, cfg.trajectory, None, generator)]
            round_index += 1
        return drawn[:count]

    if cfg.shared_trajectories:
        drawn = trajectories(min(cfg.student_views), trajectory_count(cfg))
        return [{**drawn[c // len(cfg.student_views)], "views": views, "trajectory": c // len(cfg.student_views)}
                for c, views in enumerate(counts)]
    per_count = {views: iter(trajectories(views, counts.count(views))) for views in cfg.student_views}
    return [{**next(per_count[views]), "views": views, "trajectory": c} for c, views in enumerate(counts)]


def frames_stored(cfg: PrepareConfig) -> bool:
    """Whether shards keep uint8 frames: ``store_frames``, or by default only a held-out split's cache, whose
    clips evaluation scores in pixels (training reads latents only)."""
    return cfg.split != Split.train if cfg.store_frames is None else cfg.store_frames


def psnr_on_path(frames: torch.Tensor, reference: torch.Tensor) -> float:
    """PSNR on the trajectory frames, excluding the two reference frames at the clip ends."""
    return float(peak_signal_noise_ratio(frames[1:-1], reference[1:-1], data_range=1.0))


@dataclass
class EncodedClip:
    """What one clip stores: its shard's tensors (latents, poses, frames when kept) and the conditioning it
    indexes in the scene files (2D tokens per reference view, 3D tokens of the pair, the caption's text)."""

    tensors: dict[str, torch.Tensor]
    views: int
    refs: tuple[int, int]
    caption: str
    ref_2d: tuple[torch.Tensor, torch.Tensor]
    ref_3d: torch.Tensor
    text: torch.Tensor

    def scene_files(self) -> list[tuple[str, str, torch.Tensor]]:
        """(file relative to the scene folder, tensor key, tensor) of every scene file the clip indexes."""
        a, b = self.refs
        return [(cache_keys.view_tokens_file(a), cache_keys.REF_2D, self.ref_2d[0]),
                (cache_keys.view_tokens_file(b), cache_keys.REF_2D, self.ref_2d[1]),
                (cache_keys.pair_tokens_file(a, b), cache_keys.REF_3D, self.ref_3d),
                (cache_keys.text_file(self.caption), cache_keys.TEXT, self.text)]


def backbone_device(backbone: Backbone) -> torch.device:
    """The accelerator the backbone was built on."""
    return next(backbone.transformer.parameters()).device


def encode_frames(backbone: Backbone, frames: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Codec latents of named clips (each (F, 3, H, W) in [0, 1]), encoded as one batch on the backbone's device."""
    if not frames:
        return {}
    latents = backbone.codec.encode(torch.stack([clip.cpu() for clip in frames.values()]).to(backbone_device(backbone)))
    return dict(zip(frames, latents))


def stored_tokens(latents: dict[str, torch.Tensor], references: tuple[torch.Tensor, torch.Tensor],
                  text: torch.Tensor, dtype: torch.dtype
                  ) -> tuple[dict[str, torch.Tensor], tuple[torch.Tensor, torch.Tensor], torch.Tensor, torch.Tensor]:
    """What a shard and its scene files store, in the cache's dtype: the codec latents of every condition and the
    target, the 2D tokens of each reference view, the pair's 3D tokens and the text embedding."""
    ref_2d, ref_3d = references
    # The encoder returns both views' 2D tokens concatenated, first view first, each computed from its view
    # alone (DINOv2 per view), so each half is that view's tokens in any pair.
    first, second = ref_2d[0].to("cpu", dtype).chunk(2)
    return ({cache_keys.latent(k): latent.to("cpu", dtype) for k, latent in latents.items()},
            (first.clone(), second.clone()), ref_3d[0].to("cpu", dtype), text[0].to("cpu", dtype))


def scene_file_is_valid(path: Path, key: str, settings: str) -> bool:
    """A scene file exists, holds ``key`` with the bytes its checksum was written for, and was made with
    ``settings`` (another run's tokens or embeddings are not this run's)."""
    try:
        with safe_open(str(path), framework="pt") as f:
            if key not in f.keys() or (f.metadata() or {}).get("settings") != settings:
                return False
    except (SafetensorError, OSError, ValueError):
        return False
    return checksum_problem(path, [key]) is None


def write_clip(scene_dir: Path, index: int, clip: EncodedClip, metadata: dict[str, str], settings: str) -> Path:
    """Write one clip: first the scene files it indexes that are not there yet (reference tokens, text), then
    its shard, so a finished shard always finds its scene files. Every file atomic, with checksums."""
    for rel, key, tensor in clip.scene_files():
        if not scene_file_is_valid(scene_dir / rel, key, settings):
            save_safetensors_atomic({key: tensor}, scene_dir / rel, {"settings": settings})
    path = scene_dir / cache_keys.clip_file(index)
    save_safetensors_atomic(clip.tensors, path, {
        **metadata, "caption": clip.caption, cache_keys.META_VIEWS: str(clip.views),
        cache_keys.META_REFS: json.dumps(list(clip.refs)), cache_keys.META_TEXT: cache_keys.text_file(clip.caption),
        "settings": settings})
    return path


def shard_is_valid(path: Path, settings: str | None = None, images: list[int] | None = None) -> bool:
    """A shard exists, is readable, matches the checksum written with it, holds only finite numbers, (if
    given) was made with ``settings`` and records the captured ``images`` of a held-out clip (a capture order
    that changed, or a shard from before the record, is not this clip), and the scene files it indexes are
    there and intact.

    Atomic writes make partial files impossible, but a disk or a user can still change their bytes, a shard
    made with other settings is not a finished unit of this run, and one with NaN would poison training.
    """
    try:
        tensors, metadata = read_safetensors(path, fix="")
        record = clip_record(path.parent.name, 0, path)
    except (InputFileError, CacheError):
        return False
    if checksum_problem(path):
        return False
    made_with = metadata.get("settings")
    if not (cache_keys.latent(cache_keys.TARGET) in tensors and (settings is None or made_with == settings)
            and (images is None or record.captured_images() == images) and not non_finite_keys(tensors)):
        return False
    return all(scene_file_is_valid(file, key, made_with) for file, key in record.conditioning_files())


def restorer_pipeline(backbone: Backbone):
    """The frozen pseudo-target generator (supplement A.4): the pretrained restorer itself, no adapter.

    GSFixer releases one transformer folder, so theta with phi_pre is that folder: the generator is the frozen
    base, which is also variant (A) and Stage 1's starting point (B = 0 at attachment, Eq. supp-lora).
    """
    from tracegs.restorer.sampler import RestorationPipeline

    return RestorationPipeline(backbone)


@dataclass
class SharedTrajectory:
    """What the clips of one trajectory have in common under ``shared_trajectories`` (paper: 25 trajectories x 3 K
    per scene): its pseudo-target and the codec latents of its teacher conditions and target. Its first clip makes
    them, the trajectory's other clips (consecutive) reuse them, so R_d is encoded and restored once per
    trajectory, not once per clip."""

    trajectory: int | None = None
    target: torch.Tensor | None = None
    latents: dict[str, torch.Tensor] = field(default_factory=dict)


def pseudo_target(plan: ScenePlan, clip: dict, index: int, conditions: dict[str, torch.Tensor],
                  ground_truth: torch.Tensor | None, dense_latent: torch.Tensor | None,
                  references: tuple[torch.Tensor, torch.Tensor], caption: str, cfg: PrepareConfig,
                  backbone: Backbone, pipeline) -> torch.Tensor:
    """The clip's target frames: ground truth, R_d itself, or R_d restored by the frozen restorer from its codec
    latent ``dense_latent`` (supplement A.4). A restoration shared by a trajectory's clips is captioned from R_d
    and seeded by the trajectory, which its clips have in common, so a resumed preparation makes the same one."""
    if cfg.pseudo_target == "gt":
        return ground_truth
    dense = conditions[dense_condition(cfg)]
    if cfg.pseudo_target == "dense":
        return dense
    if cfg.shared_trajectories:
        seed = scene_seed(cfg.seed, f"{plan.scene.name}/trajectory{clip['trajectory']}")
        caption = clip_caption(cfg.captions, dense[0], plan.scene.caption)
    else:
        seed = scene_seed(cfg.seed, f"{plan.scene.name}/{index}")
    latents = pipeline.restore_latents(dense_latent[None], *references, backbone.text_encoder.encode([caption]),
                                       seed=seed, guidance_scale=cfg.pseudo_target_guidance)
    return backbone.codec.decode(latents)[0].clamp(0, 1).cpu()


def clip_latents(plan: ScenePlan, clip: dict, index: int, conditions: dict[str, torch.Tensor],
                 ground_truth: torch.Tensor | None, references: tuple[torch.Tensor, torch.Tensor], caption: str,
                 cfg: PrepareConfig, backbone: Backbone, pipeline, shared: SharedTrajectory
                 ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The clip's pseudo-target and the codec latents of its conditions and target (key ``target``).

    Without shared trajectories a clip's conditions and target are one batch (a restored target: the conditions
    first, R_d's latent restored, then the target). With them, ``shared`` holds the trajectory's teacher
    latents, pseudo-target and target latent (made as one batch of teacher conditions, then the target, by
    whichever of its clips comes first, also on a resumed run), and each clip encodes its own student conditions
    only."""
    dense = dense_condition(cfg)
    # A held-out clip through captured photographs (tracegs.data.held_out) belongs to no drawn trajectory.
    if not cfg.shared_trajectories or "trajectory" not in clip:
        if cfg.pseudo_target != "restorer":
            target = pseudo_target(plan, clip, index, conditions, ground_truth, None, references, caption, cfg,
                                   backbone, pipeline)
            return target, encode_frames(backbone, {**conditions, cache_keys.TARGET: target})
        latents = encode_frames(backbone, conditions)
        target = pseudo_target(plan, clip, index, conditions, ground_truth, latents[dense], references, caption, cfg,
                               backbone, pipeline)
        return target, latents | encode_frames(backbone, {cache_keys.TARGET: target})
    teacher = {condition_key(count) for count in teacher_view_counts(cfg)}
    if shared.trajectory != clip["trajectory"]:
        latents = encode_frames(backbone, {k: frames for k, frames in conditions.items() if k in teacher})
        target = pseudo_target(plan, clip, index, conditions, ground_truth, latents.get(dense), references, caption,
                               cfg, backbone, pipeline)
        latents |= encode_frames(backbone, {cache_keys.TARGET: target})
        shared.trajectory, shared.target, shared.latents = clip["trajectory"], target, latents
    own = encode_frames(backbone, {k: frames for k, frames in conditions.items() if k not in teacher})
    return shared.target, {k: own[k] if k in own else shared.latents[k] for k in [*conditions, cache_keys.TARGET]}


def save_clip(plan: ScenePlan, clip: dict, index: int, conditions: dict[str, torch.Tensor],
              ground_truth: torch.Tensor | None, cfg: PrepareConfig, backbone: Backbone, pipeline,
              scene_dir: Path, settings: str, shared: SharedTrajectory, sheet: Path | None = None) -> None:
    """Pseudo-target and codec latents (``clip_latents``; ``shared``: the trajectory's, reused by its clips), the
    frozen encoders' tokens and files of one rendered clip (each condition's PSNR vs GT in its metadata); with
    ``sheet``, the contact sheet of its frames too (before its shard, so a finished shard has its sheet)."""
    cameras: list[Camera] = clip["cameras"]
    views = clip["views"]
    a, b = clip["refs"]
    ref_images = torch.stack([plan.scene.load_image(a), plan.scene.load_image(b)])
    # One caption per clip, from the first frame of its earliest-snapshot R_s (the paper does not say which of
    # the clip's R_s; the most degraded one is what deployment from K views renders first).
    student = condition_key(views, min(cfg.student_snapshots))
    caption = clip_caption(cfg.captions, conditions[student][0], plan.scene.caption)
    with torch.no_grad():
        references = backbone.reference_encoder(ref_images[None].to(backbone_device(backbone)))
        target, latents = clip_latents(plan, clip, index, conditions, ground_truth, references, caption, cfg,
                                       backbone, pipeline, shared)
        tensors, ref_2d, ref_3d, text = stored_tokens(latents, references, backbone.text_encoder.encode([caption]),
                                                      getattr(torch, cfg.latent_dtype))
    pixels = {**conditions, cache_keys.TARGET: target, cache_keys.REFERENCE: ref_images}
    if ground_truth is not None:
        pixels[cache_keys.GROUND_TRUTH] = ground_truth
    if sheet is not None:
        contact_sheet(pixels, sheet, [k for k in (student, dense_condition(cfg)) if k is not None])
    if frames_stored(cfg):
        tensors.update({cache_keys.frames(key): to_uint8(frames) for key, frames in pixels.items()})
    tensors[cache_keys.POSES] = torch.stack([c.world_to_camera for c in cameras]).float()
    tensors[cache_keys.INTRINSICS] = torch.stack([c.K for c in cameras]).float()
    psnr = {}
    if ground_truth is not None:
        psnr = {key: psnr_on_path(frames, ground_truth) for key, frames in conditions.items()}
    metadata = {"scene": plan.scene.name, "clip": str(index), "pseudo_target": cfg.pseudo_target,
                "psnr_vs_gt": json.dumps(psnr)}
    if "images" in clip:
        metadata |= {cache_keys.META_CAPTURED_IMAGES: json.dumps(clip["images"]),
                     cache_keys.META_CAPTURE_ORDER: clip["capture_order"]}
    write_clip(scene_dir, index, EncodedClip(tensors, views, (a, b), caption, ref_2d, ref_3d, text), metadata,
               settings)


def dense_condition(cfg: PrepareConfig) -> str | None:
    """Condition key of the densest configured view set (all views when listed), whose R_d feeds the
    pseudo-target generator; None when no dense set is prepared (a held-out cache that only scores restorers
    from R_s against ground truth)."""
    if not cfg.dense_views:
        return None
    return condition_key(None if None in cfg.dense_views else max(cfg.dense_views))


def read_shard_psnr(path: Path) -> dict[str, float]:
    with safe_open(str(path), framework="pt") as f:
        return json.loads(f.metadata().get("psnr_vs_gt", "{}"))


def contact_sheet(pixels: dict[str, torch.Tensor], out: Path, columns: list[str]) -> None:
    """PNG with one row per frame of a clip: the listed conditions, then the target (and ground truth when
    known), from the clip's frames in [0, 1] as rendered (so a cache without stored frames has its sheet)."""
    keys = [*columns, cache_keys.TARGET] + ([cache_keys.GROUND_TRUTH] if cache_keys.GROUND_TRUTH in pixels else [])
    frames = [to_uint8(pixels[k]) for k in keys]
    rows = torch.cat([torch.cat([c[i] for c in frames], dim=2) for i in range(frames[0].shape[0])], dim=1)
    with atomic_write(out) as tmp:
        Image.fromarray(rows.permute(1, 2, 0).numpy()).save(tmp, format="PNG")


def remove_stale_temporaries(directory: Path) -> None:
    """Delete temporaries a killed run left behind (``atomic_write`` names them ``.<name>.*.tmp``)."""
    if directory.is_dir():
        for tmp in directory.rglob(".*.tmp"):
            tmp.unlink(missing_ok=True)


def worker_pool(cfg: PrepareConfig) -> WorkerPool | None:
    """Processes for generating scenes, the fits and the clip renders (``cfg.workers`` > 1), else None.

    "spawn" gives fresh interpreters, so no OpenMP / thread state is inherited through fork.
    """
    if cfg.workers <= 1:
        return None
    return WorkerPool(cfg.workers, "spawn")


def fit_all(plans: list[ScenePlan], cfg: PrepareConfig, pool: WorkerPool | None,
            progress: Progress) -> None:
    """Run every unfinished (scene, view set) fit."""
    units = [(plan, key, cfg) for plan in plans for key in plan.fits if cfg.force or not fit_done(plan, key, cfg)]
    # Longest first (a fit's cost grows with its last snapshot), so the pool does not end on one long fit.
    units.sort(key=lambda unit: -max(unit[0].fits[unit[1]]))
    task = progress.add_task("3DGS fits", total=len(units))
    plain = PlainProgress("3DGS fits", len(units))
    for done, _ in enumerate(run_units(pool, fit_view_set, units), 1):
        progress.advance(task)
        plain.update(done)


def condition_paths(plan: ScenePlan, cfg: PrepareConfig) -> dict[str, tuple[Path, int]]:
    """PLY and snapshot iteration of every cached condition: ``s{K}_it{snap}`` for the student snapshots,
    ``d{V}`` for final fits."""
    paths: dict[str, tuple[Path, int]] = {}
    for key, snapshots in plan.fits.items():
        unit = fit_unit_paths(Path(cfg.work_dir), plan.scene.name, key, snapshots, cfg.fit)
        views = None if key == "all" else int(key)
        if cfg.fit.iterations in unit:
            paths[condition_key(views)] = (unit[cfg.fit.iterations], cfg.fit.iterations)
        if views in cfg.student_views:
            for snapshot in cfg.student_snapshots:
                paths[condition_key(views, snapshot)] = (unit[snapshot], snapshot)
    return paths


def clip_condition_keys(cfg: PrepareConfig, views: int) -> list[str]:
    """The conditions a K-view clip holds: its own K's student snapshots and every teacher condition."""
    return ([condition_key(views, snapshot) for snapshot in cfg.student_snapshots]
            + [condition_key(count) for count in teacher_view_counts(cfg)])


def render_conditions(plan: ScenePlan, cameras: list[Camera], paths: dict[str, tuple[Path, int]],
                      cfg: PrepareConfig, refs: list[int], images: list[int] | None = None
                      ) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
    """Frames [F,3,H,W] (on the CPU) of every condition along one clip, rendered by deployment's clip path
    (``render_clip``, with the captured reference images ``refs`` at its ends where ``trajectory.captured_ends``),
    and of ground truth when the scene has it: the captured ``images`` the cameras are those of, or the
    ground-truth scene rendered on the background it was made with."""
    conditions = {key: render_clip(load_ply(path), cameras, cfg.fit, iteration).cpu()
                  for key, (path, iteration) in paths.items()}
    if cfg.trajectory.captured_ends:
        references = torch.stack([plan.scene.load_image(i) for i in refs])
        conditions = {key: with_captured_ends(frames, references) for key, frames in conditions.items()}
    ground_truth = None
    if images is not None:
        ground_truth = torch.stack([plan.scene.load_image(i) for i in images])
    elif (plan.scene.root / GT_PLY).is_file():
        ground_truth = torch.stack(render_images(ground_truth_model(plan.scene), cameras,
                                                 scene_background(plan.scene)))
    return conditions, ground_truth


@dataclass
class SceneClips:
    """One scene's clips, their shard paths, the ones still to make and their renders (submitted, in order)."""

    clips: list[dict] | None  # None when every clip is finished
    shard_paths: list[Path]
    settings: str
    todo: list[int]
    rendered: Iterator[tuple[dict[str, torch.Tensor], torch.Tensor | None]]


def render_scene_clips(plan: ScenePlan, cfg: PrepareConfig, backbone: Backbone,
                       pool: WorkerPool | None) -> SceneClips:
    """Submit the renders of one scene's unfinished clips (to the worker processes when there are some). The
    clips' trajectories are drawn only when one is unfinished: a finished clip's are in its shard's header, and
    drawing them is most of the time a rerun of a finished preparation would take."""
    captured = plan.captured
    count = len(captured) if captured is not None else len(clip_view_counts(cfg, plan.scene.name))
    shard_paths = [Path(cfg.cache_dir) / plan.scene.name / cache_keys.clip_file(c) for c in range(count)]
    settings = clip_settings(cfg, backbone)
    todo = [c for c, p in enumerate(shard_paths)
            if cfg.force or not shard_is_valid(p, settings, None if captured is None else captured[c]["images"])]
    clips = clip_cameras(plan, cfg) if todo else None
    paths = condition_paths(plan, cfg)
    rendered = run_units(pool, render_conditions, [
        (plan, clips[c]["cameras"], {key: paths[key] for key in clip_condition_keys(cfg, clips[c]["views"])}, cfg,
         clips[c]["refs"], clips[c].get("images")) for c in todo])
    return SceneClips(clips, shard_paths, settings, todo, rendered)


def prepare_all_scenes(plans: list[ScenePlan], cfg: PrepareConfig, backbone: Backbone, pipeline,
                       pool: WorkerPool | None, progress: Progress) -> dict[str, dict]:
    """Every scene's clips (fits done); returns the manifest entries. Rendering runs in the worker processes
    and the frozen encoders (paper scale: GPU) in this one; the next scene's renders are submitted before
    this scene's clips are encoded, so the workers do not wait for this process between scenes (and at most
    two scenes' frames are held at once)."""
    entries: dict[str, dict] = {}
    task = progress.add_task("paired clips", total=len(plans))
    upcoming = render_scene_clips(plans[0], cfg, backbone, pool) if plans else None
    for index, plan in enumerate(plans):
        current = upcoming
        if index + 1 < len(plans):
            upcoming = render_scene_clips(plans[index + 1], cfg, backbone, pool)
        entries[plan.scene.name] = prepare_scene(plan, cfg, backbone, pipeline, current, progress)
        progress.advance(task)
    return entries


def prepare_scene(plan: ScenePlan, cfg: PrepareConfig, backbone: Backbone, pipeline, scene_clips: SceneClips,
                  progress: Progress) -> dict:
    """The clips, scene file and contact sheet (of the first clip, made with it) of one scene (its renders
    submitted); returns its manifest entry."""
    name = plan.scene.name
    cache_dir = Path(cfg.cache_dir)
    clips, shard_paths, todo = scene_clips.clips, scene_clips.shard_paths, scene_clips.todo
    clip_task = progress.add_task(f"{name}: clips", total=len(shard_paths), completed=len(shard_paths) - len(todo))
    plain = PlainProgress(f"{name}: clips", len(todo))
    sheet = cache_dir / name / "contact_sheet.png" if cfg.contact_sheet else None
    shared = SharedTrajectory()
    for done, (c, (conditions, ground_truth)) in enumerate(zip(todo, scene_clips.rendered), 1):
        save_clip(plan, clips[c], c, conditions, ground_truth, cfg, backbone, pipeline, cache_dir / name,
                  scene_clips.settings, shared, sheet if c == 0 else None)
        progress.advance(clip_task)
        plain.update(done)
    remove_unindexed_scene_files(cache_dir / name, shard_paths)
    if clips is None:  # every clip finished: its reference views and K are in its shard's header
        records = [clip_record(name, c, path) for c, path in enumerate(shard_paths)]
        clip_refs, clip_views = [list(record.refs) for record in records], [record.views for record in records]
    else:
        clip_refs, clip_views = [clip["refs"] for clip in clips], [clip["views"] for clip in clips]
    scene_file = cache_dir / name / "scene.json"
    scene_info = {
        "name": name,
        "caption": plan.scene.caption or cfg.captions.fallback,
        "image_names": plan.scene.image_names,
        "split": plan.split.to_dict(),
        "intrinsics": [c.K.tolist() for c in plan.scene.cameras],
        "world_to_camera": [c.world_to_camera.tolist() for c in plan.scene.cameras],
        "size": [plan.scene.cameras[0].height, plan.scene.cameras[0].width],
        "clip_refs": clip_refs,
        "clip_views": clip_views,
    }
    write_if_changed(scene_info, scene_file)
    psnr: dict[str, list[float]] = {}
    for path in shard_paths:
        for key, value in read_shard_psnr(path).items():
            psnr.setdefault(key, []).append(value)
    captured = {} if plan.captured is None else {
        # the rule of tracegs/data/held_out.py that ordered the capture
        "capture_order": plan.captured[0]["capture_order"],
        "padded_clips": [c for c, clip in enumerate(plan.captured) if repeats_frames(clip["images"])],
    }
    return {
        "scene_file": str(scene_file.relative_to(cache_dir)),
        "caption": scene_info["caption"],
        "clips": [str(p.relative_to(cache_dir)) for p in shard_paths],
        "psnr_vs_gt": {k: float(np.mean(v)) for k, v in psnr.items()},
        **captured,
    }


def remove_unindexed_scene_files(scene_dir: Path, shard_paths: list[Path]) -> None:
    """Delete reference-token and text files no clip indexes any more (left by a run with other settings)."""
    indexed = {path for shard in shard_paths for path, _ in clip_record(scene_dir.name, 0, shard).conditioning_files()}
    for folder in {path.parent for path in indexed}:
        for path in folder.glob("*.safetensors"):
            if path not in indexed:
                path.unlink()


def write_if_changed(data: dict, path: Path) -> None:
    """Atomic JSON write that leaves an identical file untouched (a rerun with no work changes nothing)."""
    if path.is_file():
        try:
            if json.loads(path.read_text()) == json.loads(json.dumps(data)):
                return
        except ValueError:
            pass
    write_json_atomic(data, path)


def manifest_header(cfg: PrepareConfig, backbone_name: str) -> dict:
    return {
        "version": CACHE_VERSION,
        "student_views": list(cfg.student_views),
        "student_snapshots": list(cfg.student_snapshots),
        "teacher_views": sorted({view_set_key(v) for v in teacher_view_counts(cfg)}, key=_view_order),
        "final_snapshot": cfg.fit.iterations,
        "frames_per_clip": cfg.frames_per_clip,
        "frames_stored": frames_stored(cfg),
        "pseudo_target": cfg.pseudo_target,
        "backbone": backbone_name,
    }


def _view_order(key: str) -> float:
    return math.inf if key == "all" else float(key)


def shard_manifest_path(cache_dir: Path, shard_index: int, num_shards: int) -> Path:
    if num_shards == 1:
        return cache_dir / MANIFEST
    return cache_dir / f"manifest_shard{shard_index:03d}_of{num_shards:03d}.json"


def merge_manifests(cache_dir: str | Path, num_shards: int) -> Path | None:
    """Join the manifests of the ``num_shards`` shards of a cache into ``manifest.json`` once every shard has
    written its own (their settings must agree); None, logging how many are left, while some shard has not.

    Every shard calls it as it ends, so the last to finish merges; shards that finish together write the same
    bytes, each atomically, and a rerun leaves an identical manifest untouched."""
    cache_dir = Path(cache_dir)
    parts = [shard_manifest_path(cache_dir, index, num_shards) for index in range(num_shards)]
    left = sum(not part.is_file() for part in parts)
    if left:
        log.info("%s: %d of %d shards still to finish; the last to finish merges their manifests", cache_dir,
                 left, num_shards)
        return None
    merged: dict | None = None
    for part in parts:
        data = json.loads(part.read_text())
        header = {k: v for k, v in data.items() if k != "scenes"}
        if merged is None:
            merged = {**header, "scenes": {}}
        elif header != {k: v for k, v in merged.items() if k != "scenes"}:
            raise PrepareError(f"{part}: settings differ from {parts[0].name}; shards of different runs")
        merged["scenes"].update(data["scenes"])
    merged["scenes"] = dict(sorted(merged["scenes"].items()))
    out = cache_dir / MANIFEST
    write_if_changed(merged, out)
    return out


def run_prepare(prepare: PrepareConfig, source: SceneSourceConfig, backbone: Backbone,
                synthetic: SyntheticConfig | None = None, progress: bool = True) -> Path:
    """Prepare the paired-clip cache and return the path of this shard's manifest (the last shard of a sharded
    run to finish also merges every shard's manifest into the cache's: ``merge_manifests``).

    With ``synthetic`` given, the benchmark is generated first (idempotent) and, unless ``source.scenes``
    names scenes, the seeds of its ``prepare.split`` are prepared (``test``: a held-out cache that only
    evaluation reads). A real dataset prepares its training scenes, or with ``split=test`` its test scenes'
    held-out clips through captured cameras (``data.held_out``). Every scene of the shard is loaded and split before
    anything is written, so bad input fails without side effects.
    """
    prepare = as_prepared(prepare, synthetic is not None)
    require_inputs(prepare)
    require_writable_dir(prepare.cache_dir, "data.prepare.cache_dir", finished_ok=True)
    require_writable_dir(prepare.work_dir, "data.prepare.work_dir", finished_ok=True)
    if synthetic is not None:
        require_writable_dir(synthetic.root, "data.synthetic.root", finished_ok=True)
    threads = torch.get_num_threads()
    if prepare.workers > 1:
        # The workers take the other cores; oversubscribed intra-op threads are much slower (5x measured).
        torch.set_num_threads(1)
    pool = worker_pool(prepare)
    try:
        return _run_prepare(pool, prepare, source, backbone, synthetic, progress)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        torch.set_num_threads(threads)


def _run_prepare(pool: WorkerPool | None, prepare: PrepareConfig, source: SceneSourceConfig,
                 backbone: Backbone, synthetic: SyntheticConfig | None, progress: bool) -> Path:
    if synthetic is not None:
        generate_benchmark(synthetic, splits=(prepare.split,), progress=progress, pool=pool)
        names = list(source.scenes) if source.scenes is not None else benchmark_scene_names(synthetic, prepare.split)
    else:
        names = list_scenes(source, "test" if captures_held_out(source, prepare) else "train")
    names = shard_scenes(names, prepare.shard_index, prepare.num_shards)
    if not names:
        raise PrepareError(f"{source.root}: no scenes for shard {prepare.shard_index}/{prepare.num_shards}")
    plans = []
    for name in names:
        try:
            plans.append(plan_scene(source, prepare, name))
        except (SceneFormatError, ValueError) as error:
            raise PrepareError(f"scene {name}: {error}") from error
    pipeline = restorer_pipeline(backbone) if prepare.pseudo_target == "restorer" else None
    cache_dir = Path(prepare.cache_dir)
    for plan in plans:
        for directory in (cache_dir / plan.scene.name, Path(prepare.work_dir) / plan.scene.name):
            remove_stale_temporaries(directory)
    with Progress(disable=not progress) as bar:
        fit_all(plans, prepare, pool, bar)
        entries = prepare_all_scenes(plans, prepare, backbone, pipeline, pool, bar)
    manifest = {**manifest_header(prepare, backbone.cfg.name), "scenes": entries}
    path = shard_manifest_path(cache_dir, prepare.shard_index, prepare.num_shards)
    write_if_changed(manifest, path)
    if prepare.num_shards > 1:
        merge_manifests(cache_dir, prepare.num_shards)
    return path
