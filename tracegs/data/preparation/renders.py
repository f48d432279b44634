"""The renders of a scene's clips: every condition (and ground truth where the scene has it) along each
unfinished clip's trajectory, submitted to the worker processes one scene ahead of encoding.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch

from tracegs.data import cache_keys
from tracegs.data.config import PrepareConfig
from tracegs.data.preparation.fits import condition_paths
from tracegs.data.preparation.plan import ScenePlan, clip_cameras, clip_condition_keys, clip_view_counts
from tracegs.data.preparation.shards import clip_settings, shard_is_valid
from tracegs.data.synthetic import GT_PLY, ground_truth_model, render_images, scene_background
from tracegs.processes import WorkerPool, run_units
from tracegs.restorer.build import Backbone
from tracegs.splat.cameras import Camera
from tracegs.splat.ply import load_ply
from tracegs.splat.render import render_clip
from tracegs.splat.trajectory import with_captured_ends


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
