"""A preparation run end to end: the worker pool, every scene planned before anything is written, the fits,
then each scene's clips, scene file and manifest entry.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from rich.progress import Progress

from tracegs.console import PlainProgress
from tracegs.data.colmap import SceneFormatError, list_scenes
from tracegs.data.config import PrepareConfig, SceneSourceConfig, SyntheticConfig, as_prepared
from tracegs.data.datamodule import clip_record, repeats_frames
from tracegs.data.preparation.encode import SharedTrajectory, restorer_pipeline, save_clip
from tracegs.data.preparation.fits import fit_all
from tracegs.data.preparation.manifests import (
    manifest_header,
    merge_manifests,
    shard_manifest_path,
    write_if_changed,
)
from tracegs.data.preparation.plan import (
    PrepareError,
    ScenePlan,
    captures_held_out,
    plan_scene,
    require_inputs,
    shard_scenes,
)
from tracegs.data.preparation.renders import SceneClips, render_scene_clips
from tracegs.data.preparation.shards import read_shard_psnr, remove_unindexed_scene_files
from tracegs.data.synthetic import benchmark_scene_names, generate_benchmark
from tracegs.errors import require_writable_dir
from tracegs.processes import WorkerPool
from tracegs.restorer.build import Backbone


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
