"""Restoration quality on held-out paired clips: is a restorer's output closer to ground truth than its input?

The clips come from a cache that ``prepare`` built for scenes no restorer was trained on (the benchmark's
test scenes), with frames (``data.prepare.store_frames``, on by default for a held-out split): the synthetic
test scenes, or a real dataset's test scenes through captured cameras (``data.held_out``). Every clip
belongs to one student view count K; for each of its student conditions R_s (K views, snapshot) the restorer
runs its full deployment schedule from the cached latents; the decoded output and the input R_s are both
scored against the clip's ground-truth frames. The two end frames are the reference views and are excluded,
as everywhere in the evaluation. Scene averages come first, then the unweighted mean over scenes (supplement B).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from pathlib import Path

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
from tracegs.restorer.sampler import RestorationPipeline

INPUT = "input"  # the row label of the unrestored R_s


def _pixels(frames: Tensor) -> Tensor:
    """8-bit cached frames as floats in [0, 1]."""
    return frames.float() / 255.0


def trajectory_frames(tensors: dict[str, Tensor], name: str) -> Tensor:
    """The trajectory frames of a condition, ``TARGET`` or ``GROUND_TRUTH`` of a cached clip (the two reference
    frames at the ends dropped, as everywhere in the evaluation)."""
    return _pixels(tensors[cache_keys.frames(name)][1:-1])


def mean_psnr(frames: Tensor, truth: Tensor) -> float:
    """PSNR (dB) of each frame against its truth, averaged over the frames."""
    return float(peak_signal_noise_ratio(frames, truth, data_range=1.0, reduction="none", dim=(1, 2, 3)).mean())


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
        for cond in conditions:
            scores[cond][INPUT][scene].append(mean_psnr(trajectory_frames(tensors, cond), truth))
        # One batch per clip: every condition of the clip restored together, same seed across restorers.
        for label, pipeline in pipelines.items():
            for cond, frames in zip(conditions, restore_clip(pipeline, tensors, conditions, seed + index)):
                scores[cond][label][scene].append(mean_psnr(frames, truth))
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


@torch.no_grad()
def held_out_per_step_curves(pipelines: Mapping[str, RestorationPipeline], cache_dir: str | Path,
                             seed: int = 0, progress: bool = True) -> dict[str, list[float]]:
    """Fig. 6 on the held-out clips: each pipeline's per-step PSNR curve (``eval.per_step``), averaged across
    view settings (``view_averaged_curves``). The same clips, conditions and noise seeds go to every pipeline."""
    return view_averaged_curves(unit_curves(held_out_clip_curves(pipelines, cache_dir, seed, progress)))


def unit_curves(clip_curves: list[tuple[str, int, dict[str, list[float]]]]
                ) -> dict[tuple[str, str], dict[str, list[float]]]:
    """Each (scene, K)'s per-step curves, the mean over its clips: the units of the intervals over scenes."""
    units: dict[tuple[str, str], list[dict[str, list[float]]]] = defaultdict(list)
    for scene, views, curves in clip_curves:
        units[(scene, str(views))].append(curves)
    return {unit: mean_curves(curves) for unit, curves in units.items()}


def view_averaged_curves(units: Mapping[tuple[str, str], Mapping[str, list[float]]]) -> dict[str, list[float]]:
    """Fig. 6's curve: per view setting K the mean over scenes, then the mean over the K (the caption's "averaged
    across view settings"), so a K with more clips per scene (one per reference pair) weighs no more."""
    views = dict.fromkeys(k for _, k in units)
    return mean_curves([mean_curves([c for (_, k), c in units.items() if k == view]) for view in views])


@torch.no_grad()
def held_out_clip_curves(pipelines: Mapping[str, RestorationPipeline], cache_dir: str | Path,
                         seed: int = 0, progress: bool = True) -> list[tuple[str, int, dict[str, list[float]]]]:
    """(scene, student view count K, each pipeline's per-step curve averaged over the student conditions) of
    every held-out clip."""
    curves = []
    for index, clip in enumerate(track(held_out_clips(cache_dir), description="per-step curves",
                                       disable=not progress)):
        scene, conditions = clip.scene, clip.conditions()
        tensors = load_clip(clip)
        frames = torch.stack([_pixels(tensors[cache_keys.frames(c)]) for c in conditions])
        truth = _pixels(tensors[cache_keys.frames(cache_keys.GROUND_TRUTH)]).expand(len(conditions), -1, -1, -1, -1)
        refs = _pixels(tensors[cache_keys.frames(cache_keys.REFERENCE)]).expand(len(conditions), -1, -1, -1, -1)
        caption = clip.metadata.get("caption", "")
        curves.append((scene, clip.views, {label: per_step_psnr(pipeline, frames, refs, [caption] * len(conditions),
                                                                truth, seed=seed + index)
                                           for label, pipeline in pipelines.items()}))
    return curves
