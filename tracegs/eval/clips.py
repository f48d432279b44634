"""Restoration quality on held-out paired clips: is a restorer's output closer to ground truth than its input?

The clips come from a cache that ``prepare`` built for scenes no restorer was trained on (the benchmark's
test scenes), with frames (``data.prepare.store_frames``, on by default for a held-out split): the synthetic
test scenes, or a real dataset's test scenes through captured cameras (``data.held_out``). Every clip
belongs to one student view count K; for each of its student conditions R_s (K views, snapshot) the restorer
runs its full deployment schedule from the cached latents; the decoded output and the input R_s are both
scored against the clip's ground-truth frames. The two end frames are the reference views and are excluded,
as everywhere in the evaluation. Scene averages come first, then the unweighted mean over scenes (supplement B).

A clip's score is its mean over frames with each distinct ground-truth frame counted once: a padded captured
clip (``data.prepare.held_out_repeat_frames``) repeats captured images, and each repeated image's copies share
one frame's weight (``distinct_frame_weights``); Fig. 6 is also reported over the unpadded and the padded
clips apart, and at K = 3 alone (``per_step_breakdown``).
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import torch
from rich.progress import track
from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio

from tracegs.data import cache_keys
from tracegs.data.datamodule import (
    CacheError,
    ClipRecord,
    manifest_clips,
    read_conditioning,
    read_manifest,
    read_tensors,
    verify_clip,
)
from tracegs.eval.per_step import mean_curves, per_step_psnr
from tracegs.eval.trajectory import frame_mean
from tracegs.restorer.sampler import RestorationPipeline

INPUT = "input"  # the row label of the unrestored R_s


def _pixels(frames: Tensor) -> Tensor:
    """8-bit cached frames as floats in [0, 1]."""
    return frames.float() / 255.0


def trajectory_frames(tensors: dict[str, Tensor], name: str) -> Tensor:
    """The trajectory frames of a condition, ``TARGET`` or ``GROUND_TRUTH`` of a cached clip (the two reference
    frames at the ends dropped, as everywhere in the evaluation)."""
    return _pixels(tensors[cache_keys.frames(name)][1:-1])


def mean_psnr(frames: Tensor, truth: Tensor, weights: Tensor | None = None) -> float:
    """PSNR (dB) of each frame against its truth, averaged over the frames (with ``weights``: ``frame_mean``)."""
    per_frame = peak_signal_noise_ratio(frames, truth, data_range=1.0, reduction="none", dim=(1, 2, 3))
    return float(frame_mean(per_frame, weights))


def distinct_frame_weights(clip: ClipRecord) -> Tensor | None:
    """Weights of a clip's trajectory frames (reference ends dropped) that count each distinct captured image
    once: 1 / (its multiplicity x the number of distinct images); None for a clip whose frames are all distinct
    (the plain mean)."""
    if not clip.padded:
        return None
    interior = clip.captured_images()[1:-1]
    multiplicity = Counter(interior)
    return torch.tensor([1.0 / (multiplicity[i] * len(multiplicity)) for i in interior], dtype=torch.float64)


def _scene_mean(per_scene: Mapping[str, list[float]]) -> float:
    return sum(sum(v) / len(v) for v in per_scene.values()) / len(per_scene)


def held_out_clips(cache_dir: str | Path) -> list[ClipRecord]:
    """The clips of a prepared cache, in manifest order; every shard and the scene files it indexes are verified
    against their checksums first, so a damaged one stops the evaluation before any work."""
    manifest = read_manifest(cache_dir)
    clips = manifest_clips(cache_dir, manifest, list(manifest["scenes"]))
    for clip in clips:
        verify_clip(clip)
    return clips


def load_clip(clip: ClipRecord) -> dict[str, Tensor]:
    """One held-out clip's tensors with its reference tokens and text embedding gathered; it must carry
    ground-truth frames."""
    if cache_keys.frames(cache_keys.GROUND_TRUTH) not in clip.keys:
        raise CacheError(f"{clip.path}: no ground-truth frames; clip quality needs a scene with known ground truth "
                         "and a cache prepared with frames (data.prepare.store_frames)")
    return {**read_tensors(clip.path, sorted(clip.keys)), **read_conditioning(clip)}


def restore_clip(pipeline: RestorationPipeline, tensors: dict[str, Tensor], keys: list[str], seed: int) -> Tensor:
    """The restored trajectory frames (B, T-2, 3, H, W) of a cached clip from each condition in ``keys``, in one
    batch with one noise seed: decoded to pixels, the two reference frames at the ends dropped."""
    batch = len(keys)
    latents = pipeline.restore_latents(
        torch.stack([tensors[cache_keys.latent(key)].float() for key in keys]),
        tensors[cache_keys.REF_2D].float().expand(batch, -1, -1),
        tensors[cache_keys.REF_3D].float().expand(batch, -1, -1),
        tensors[cache_keys.TEXT].float().expand(batch, -1, -1),
        seed=seed,
    )
    return pipeline.backbone.codec.decode(latents).cpu()[:, 1:-1]


@torch.no_grad()
def clip_restoration_psnr(pipelines: Mapping[str, RestorationPipeline], cache_dir: str | Path,
                          seed: int = 0, progress: bool = True) -> dict:
    """PSNR (dB) of R_s and of each pipeline's restoration against ground truth, per student condition.

    Returns ``{"conditions": {cond: {label: psnr}}, "mean": {label: psnr}, "clips": n, "scenes": [...]}``
    where ``label`` is ``"input"`` or a key of ``pipelines``; ``mean`` averages over conditions.
    """
    shards = held_out_clips(cache_dir)
    scores: dict[str, dict[str, dict[str, list[float]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for index, clip in enumerate(track(shards, description="held-out clips", disable=not progress)):
        scene, conditions = clip.scene, clip.conditions()
        tensors = load_clip(clip)
        truth = trajectory_frames(tensors, cache_keys.GROUND_TRUTH)
        weights = distinct_frame_weights(clip)
        for cond in conditions:
            scores[cond][INPUT][scene].append(mean_psnr(trajectory_frames(tensors, cond), truth, weights))
        # One batch per clip: every condition of the clip restored together, same seed across restorers.
        for label, pipeline in pipelines.items():
            for cond, frames in zip(conditions, restore_clip(pipeline, tensors, conditions, seed + index)):
                scores[cond][label][scene].append(mean_psnr(frames, truth, weights))
    per_condition = {cond: {label: _scene_mean(by_scene) for label, by_scene in rows.items()}
                     for cond, rows in scores.items()}
    labels = [INPUT, *pipelines]
    scenes = sorted({clip.scene for clip in shards})
    return {
        "conditions": per_condition,
        "mean": {label: sum(row[label] for row in per_condition.values()) / len(per_condition) for label in labels},
        "clips": len(shards),
        "scenes": scenes,
        # Each scene's mean over its clips, per condition: the unit of the report's intervals over scenes.
        "per_scene": {scene: {cond: {label: sum(by_scene[scene]) / len(by_scene[scene])
                                     for label, by_scene in rows.items()} for cond, rows in scores.items()}
                      for scene in scenes},
    }


class ClipCurves(NamedTuple):
    """One held-out clip's per-step curves (one per pipeline, averaged over its student conditions)."""

    scene: str
    views: int
    padded: bool
    capture_order: str | None  # the rule its captured frames were ordered by; None for a rendered trajectory
    curves: dict[str, list[float]]


def unit_curves(clip_curves: Sequence[ClipCurves]) -> dict[tuple[str, str], dict[str, list[float]]]:
    """Each (scene, K)'s per-step curves, the mean over its clips: the units of the intervals over scenes."""
    units: dict[tuple[str, str], list[dict[str, list[float]]]] = defaultdict(list)
    for clip in clip_curves:
        units[(clip.scene, str(clip.views))].append(clip.curves)
    return {unit: mean_curves(curves) for unit, curves in units.items()}


def view_averaged_curves(units: Mapping[tuple[str, str], Mapping[str, list[float]]]) -> dict[str, list[float]]:
    """Fig. 6's curve: per view setting K the mean over scenes, then the mean over the K (the caption's "averaged
    across view settings"), so a K with more clips per scene (one per reference pair) weighs no more."""
    views = dict.fromkeys(k for _, k in units)
    return mean_curves([mean_curves([c for (_, k), c in units.items() if k == view]) for view in views])


@torch.no_grad()
def held_out_clip_curves(pipelines: Mapping[str, RestorationPipeline], cache_dir: str | Path,
                         seed: int = 0, progress: bool = True) -> list[ClipCurves]:
    """Every held-out clip's per-step curves, each distinct ground-truth frame counted once."""
    curves = []
    for index, clip in enumerate(track(held_out_clips(cache_dir), description="per-step curves",
                                       disable=not progress)):
        scene, conditions = clip.scene, clip.conditions()
        tensors = load_clip(clip)
        frames = torch.stack([_pixels(tensors[cache_keys.frames(c)]) for c in conditions])
        truth = _pixels(tensors[cache_keys.frames(cache_keys.GROUND_TRUTH)]).expand(len(conditions), -1, -1, -1, -1)
        refs = _pixels(tensors[cache_keys.frames(cache_keys.REFERENCE)]).expand(len(conditions), -1, -1, -1, -1)
        captions = [clip.metadata.get("caption", "")] * len(conditions)
        weights = distinct_frame_weights(clip)
        curves.append(ClipCurves(scene, clip.views, clip.padded, clip.metadata.get(cache_keys.META_CAPTURE_ORDER),
                                 {label: per_step_psnr(pipeline, frames, refs, captions, truth, seed=seed + index,
                                                       frame_weights=weights)
                                  for label, pipeline in pipelines.items()}))
    return curves


BREAKDOWN_VIEWS = 3  # the K reported alone beside Fig. 6's mean over K (the sparsest of the paper's settings)


def per_step_breakdown(clip_curves: Sequence[ClipCurves]) -> dict:
    """Fig. 6's curve (``view_averaged_curves``) and K = 3's alone, over all clips, over the unpadded and over
    the padded ones: ``{"rows": [{"clips", "views", "count", "curves"}], "capture_order": {rule: [scenes]}}``;
    ``curves`` is None for a row with no clips."""
    rows = []
    for subset, keep in (("all", lambda c: True), ("unpadded", lambda c: not c.padded),
                         ("padded", lambda c: c.padded)):
        chosen = [c for c in clip_curves if keep(c)]
        at_k = [c for c in chosen if c.views == BREAKDOWN_VIEWS]
        for views, clips in (("mean over K", chosen), (f"K = {BREAKDOWN_VIEWS}", at_k)):
            rows.append({"clips": subset, "views": views, "count": len(clips),
                         "curves": view_averaged_curves(unit_curves(clips)) if clips else None})
    orders: dict[str, list[str]] = defaultdict(list)
    for clip in clip_curves:
        rule = clip.capture_order or "rendered trajectory (no capture order)"
        if clip.scene not in orders[rule]:
            orders[rule].append(clip.scene)
    return {"rows": rows, "capture_order": dict(orders)}


def per_step_breakdown_markdown(breakdown: Mapping) -> str:
    """The breakdown as a table: one row per clip subset, view setting and restorer, the whole curve in dB."""
    lines = ["Per-step PSNR (dB) of the x0 prediction, first reverse step to last; each distinct ground-truth "
             "frame counted once. Padded clips repeat captured frames (data.prepare.held_out_repeat_frames).", "",
             "| clips | views | count | restorer | first | last | curve |", "|---|---|---|---|---|---|---|"]
    for row in breakdown["rows"]:
        if row["curves"] is None:
            lines.append(f"| {row['clips']} | {row['views']} | 0 | - | - | - | - |")
        for label, curve in (row["curves"] or {}).items():
            lines.append(f"| {row['clips']} | {row['views']} | {row['count']} | {label} | {curve[0]:.2f} | "
                         f"{curve[-1]:.2f} | {' '.join(f'{v:.2f}' for v in curve)} |")
    orders = "; ".join(f"{rule} ({', '.join(scenes)})" for rule, scenes in breakdown["capture_order"].items())
    return "\n".join([*lines, "", f"Capture order: {orders}.", ""])
