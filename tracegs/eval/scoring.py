"""Evaluation over test scenes x view counts x methods (supplement B, "Metric computation").

Each (scene, K) unit of ``tracegs.deploy.scenes`` is fitted from V_s once, branched for every method
(plain 3DGS, the baseline restorer, TRACE-GS), and each final model is scored on the scene's test views
(never the captured/reference views); ``units/<scene>/views_<K>.json`` keeps per-view and per-scene
metrics. ``tracegs.eval.merge.merge_results`` averages each scene's test views, then scenes, into
``results.json`` and the Tables 1/2 layout. Finished units are skipped on rerun unless their settings changed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import multiprocessing
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from rich.progress import Progress
from torch import Tensor

from tracegs.console import PlainProgress
from tracegs.content import names_and_bytes_digest
from tracegs.data.captions import require_captioner
from tracegs.data.colmap import Scene, load_scene
from tracegs.data.config import SceneSourceConfig
from tracegs.data.sources import GroundTruthRenderer
from tracegs.deploy.config import METHODS, EvaluationConfig, RefinementConfig
from tracegs.deploy.refine import refine, render_round_clips, to_clip_size
from tracegs.deploy.restorers import ClipRestorer, DiffusionRestorer
from tracegs.deploy.scenes import SceneUnit, deployment_source, evaluation_units, load_unit, save_model
from tracegs.errors import NonFiniteError, require_writable_dir
from tracegs.eval.merge import merge_results, unit_path
from tracegs.eval.metrics import (
    ImageMetrics,
    mean_metrics,
    require_lpips,
    require_lpips_convention,
    require_ssim_convention,
)
from tracegs.eval.per_step import per_step_psnr
from tracegs.eval.tables_and_figures import (
    METHOD_LABELS,
    save_comparison_video,
    save_frames,
    save_qualitative_grid,
    save_view_images,
)
from tracegs.io import write_json_atomic
from tracegs.processes import die_with_parent
from tracegs.products import Product, blank_unread
from tracegs.splat.cameras import Camera
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.fit import GaussianFitter
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.render import render_views, require_available
from tracegs.splat.trajectory import bridge_poses

log = logging.getLogger("tracegs")


def test_trajectory(cameras: Sequence[Camera], frames: int) -> list[Camera]:
    """A smooth path through the test cameras (bridges between consecutive ones) for the videos, every frame at
    the first camera's size (the others ``Camera.reframed`` to it: a video has one frame size)."""
    cameras = [camera.reframed(cameras[0].width, cameras[0].height) for camera in cameras]
    if len(cameras) < 2:
        return list(cameras) * max(frames, 1)
    per_leg = max(2, frames // (len(cameras) - 1))
    path: list[Camera] = []
    for a, b in zip(cameras, cameras[1:]):
        path.extend(bridge_poses(a, b, per_leg))
    return path[:frames]

def _fingerprint(*parts) -> str:
    """Digest of everything that changes a unit's numbers, so stale units are recomputed: of a settings section,
    the fields an evaluation reads (tracegs.products)."""
    blob = json.dumps([dataclasses.asdict(blank_unread(p, Product.evaluate)) if dataclasses.is_dataclass(p) else p
                       for p in parts], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]

def require_finite_metrics(per_view: Sequence[Mapping[str, float | None]], unit: str) -> None:
    """A NaN or infinite score (a NaN render, an empty image) must not be averaged into a table."""
    for index, row in enumerate(per_view):
        bad = {name: value for name, value in row.items() if value is not None and not math.isfinite(value)}
        if bad:
            raise NonFiniteError(unit, f"non-finite metrics {bad} on test view {index}; nothing was written",
                                 "check the restorer weights and the refinement settings (deploy.*)")

@dataclass
class MethodResult:
    """One method deployed on one unit: metrics on the test views, the renders they score, the final 3DGS."""

    scores: dict
    renders: list[Tensor]
    model: GaussianModel


def deploy_method(unit: SceneUnit, cold: GaussianFitter, restorer: ClipRestorer | None, method: str,
                  refine_cfg: RefinementConfig, fit_cfg: GaussianFitConfig, metrics: ImageMetrics) -> MethodResult:
    """Refine the unit's shared cold start with one method's restorer and score it on the test views."""
    background = torch.tensor(fit_cfg.background, dtype=torch.float32)
    model = refine(cold, unit.captured, restorer, refine_cfg, fit_cfg, caption=unit.scene.caption or "",
                   seed=refine_cfg.seed)
    renders = unit.render_tests(model, background)
    per_view = metrics.per_view(renders, unit.test_images)
    require_finite_metrics(per_view, f"scene {unit.scene.name}, {unit.views} views, method {method}")
    return MethodResult({"per_view": per_view, "mean": mean_metrics(per_view)}, renders, model)


def model_path(out_dir: str | Path, scene: str, views: int, method: str) -> Path:
    return Path(out_dir) / "models" / scene / f"views_{views}_{method}.ply"

def unit_per_step_curves(unit: SceneUnit, cold: GaussianFitter, restorers: Mapping[str, ClipRestorer | None],
                         refine_cfg: RefinementConfig, fit_cfg: GaussianFitConfig,
                         gt_renderer: GroundTruthRenderer) -> dict[str, list[float]]:
    """Fig. 6 on this unit: the first round's clips rendered from the cold start (before refinement),
    restored by each diffusion restorer, scored against ground truth at every reverse step."""
    generator = torch.Generator().manual_seed(refine_cfg.seed)
    caption = unit.scene.caption or ""
    clips = render_round_clips(cold, unit.captured, 0, refine_cfg, fit_cfg, caption, generator)
    truth = torch.stack([to_clip_size(gt_renderer(unit.scene, clip.cameras), refine_cfg.clip_size)
                         for clip in clips])
    frames = torch.stack([c.frames for c in clips])
    refs = torch.stack([c.references for c in clips])
    return {
        method: per_step_psnr(restorer.pipeline, frames, refs, [c.caption for c in clips], truth, seed=refine_cfg.seed,
                              steps=restorer.steps)
        for method, restorer in restorers.items() if isinstance(restorer, DiffusionRestorer)
    }

def _save_media(unit: SceneUnit, cfg: EvaluationConfig, test_renders: Mapping[str, Tensor],
                models: Mapping[str, GaussianModel], background: Tensor,
                gt_renderer: GroundTruthRenderer | None) -> dict:
    """Qualitative grid (methods + GT on the first test views) and a video along a test trajectory (and,
    with ``cfg.save_frames``, each method's frames of it)."""
    media_dir = Path(cfg.out_dir) / "media"
    stem = f"{unit.scene.name}_views{unit.views}"
    shown = min(cfg.grid_views, len(unit.test_cameras))
    columns = {METHOD_LABELS.get(m, m): list(r[:shown]) for m, r in test_renders.items()}
    columns["GT"] = list(unit.test_images[:shown])
    grid = save_qualitative_grid(columns, media_dir / f"{stem}_grid.png")
    path = test_trajectory(unit.test_cameras, cfg.video_frames)
    frames = {METHOD_LABELS.get(m, m): render_views(model, path, background, None).cpu() for m, model in models.items()}
    if gt_renderer is not None:
        frames["GT"] = gt_renderer(unit.scene, path)
    video = save_comparison_video(frames, media_dir / f"{stem}_trajectory", fps=cfg.video_fps)
    media: dict = {"grid": str(grid), "video": str(video)}
    if cfg.save_frames:
        media["frames"] = {m: str(save_frames(frames[METHOD_LABELS.get(m, m)], media_dir / f"{stem}_frames" / m))
                           for m in models}
    return media

def _save_views(unit: SceneUnit, directory: Path) -> dict[str, dict]:
    """The unit's captured and held-out cameras (the normalised world its refined PLYs live in) with the images
    each view was fitted to or scored on, by view index: what ``tracegs-view`` shows beside the PLYs, so the
    folder holds them whether or not the scene it was made from is still where it was."""
    cameras = {**dict(zip(unit.captured_ids, (v.camera for v in unit.captured))),
               **dict(zip(unit.test_ids, unit.test_cameras))}
    images = {**dict(zip(unit.captured_ids, (v.image for v in unit.captured))),
              **dict(zip(unit.test_ids, unit.test_images))}
    paths = save_view_images(images, directory)
    return {str(view): {**camera.as_record(), "image": str(paths[view])} for view, camera in sorted(cameras.items())}


def views_path(out_dir: str | Path, scene: str, views: int) -> Path:
    return Path(out_dir) / "models" / scene / f"views_{views}_images"


PER_STEP = "per_step"  # the part of a unit that computes its Fig. 6 curves


@dataclass
class _UnitJob:
    """Everything an evaluation unit needs; handed to worker processes by fork, never pickled.

    A unit is deployed from one cold start, then in parts (each method, and the per-step curves), which are
    independent given the cold start: ``run`` does them in turn, ``_run_units`` spreads them over processes.
    """

    cfg: EvaluationConfig
    source: SceneSourceConfig
    refine_cfg: RefinementConfig
    fit_cfg: GaussianFitConfig
    restorers: Mapping[str, ClipRestorer | None]
    metrics: ImageMetrics
    gt_renderer: GroundTruthRenderer | None
    fingerprint: str
    # This process's scenes, each loaded once, and the unit whose parts run now (a unit's parts follow one another
    # in a process; keeping every unit would hold every scene's test images at once).
    scenes: dict[str, Scene] = field(default_factory=dict)
    current: tuple[tuple[str, int], SceneUnit] | None = None

    def parts(self) -> list[str]:
        """The methods, longest first (restorers run repair rounds; plain 3DGS does not), then the curves."""
        for method in self.cfg.methods:
            if method not in self.restorers:
                raise ValueError(f"evaluation.methods lists {method!r} but no restorer was built for it")
        methods = sorted(self.cfg.methods, key=lambda m: self.restorers[m] is None)
        return methods + ([PER_STEP] if self.cfg.per_step and self.gt_renderer is not None else [])

    def unit(self, key: tuple[str, int]) -> SceneUnit:
        """The (scene, K) unit, split as prepare splits it (``load_unit``)."""
        if self.current is None or self.current[0] != key:
            scene_name, views = key
            if scene_name not in self.scenes:
                self.scenes[scene_name] = load_scene(self.source, scene_name)
            self.current = (key, load_unit(self.scenes[scene_name], views, self.source))
        return self.current[1]

    def cold_start(self, key: tuple[str, int]) -> GaussianFitter:
        return self.unit(key).cold_start(self.refine_cfg, self.fit_cfg)

    def part(self, key: tuple[str, int], cold: GaussianFitter, part: str) -> MethodResult | dict:
        unit = self.unit(key)
        if part == PER_STEP:
            return unit_per_step_curves(unit, cold, self.restorers, self.refine_cfg, self.fit_cfg, self.gt_renderer)
        return deploy_method(unit, cold, self.restorers[part], part, self.refine_cfg, self.fit_cfg, self.metrics)

    def finish(self, key: tuple[str, int], parts: Mapping[str, MethodResult | dict]) -> dict:
        """The unit's record from its finished parts (plus media and saved models), written atomically."""
        unit = self.unit(key)
        cfg = self.cfg
        methods: dict[str, MethodResult] = {m: parts[m] for m in cfg.methods}
        record: dict = {"scene": unit.scene.name, "views": unit.views, "captured": unit.captured_ids,
                        "test": unit.test_ids,
                        "names": {str(view): unit.scene.image_names[view] for view in unit.captured_ids + unit.test_ids},
                        "lpips": self.metrics.lpips_label, "ssim": self.metrics.ssim_label,
                        "methods": {m: result.scores for m, result in methods.items()}}
        if PER_STEP in parts:
            record["per_step"] = parts[PER_STEP]
        models = {m: result.model for m, result in methods.items()}
        if cfg.save_media:
            background = torch.tensor(self.fit_cfg.background, dtype=torch.float32)
            record["media"] = _save_media(unit, cfg, {m: result.renders for m, result in methods.items()}, models,
                                          background, self.gt_renderer)
        if cfg.save_models:
            record["models"] = {method: str(save_model(model, model_path(cfg.out_dir, unit.scene.name, unit.views,
                                                                           method)))
                                for method, model in models.items()}
            record["cameras"] = _save_views(unit, views_path(cfg.out_dir, unit.scene.name, unit.views))
        record["fingerprint"] = self.unit_fingerprint(key)
        record["variant"] = cfg.variant
        # Paths relative to the evaluation folder: the record stays true when its root is copied or moved.
        for files in (record.get("media", {}), record.get("media", {}).get("frames", {}), record.get("models", {})):
            files.update({name: os.path.relpath(path, cfg.out_dir)
                          for name, path in files.items() if isinstance(path, str)})
        for view in record.get("cameras", {}).values():
            view["image"] = os.path.relpath(view["image"], cfg.out_dir)
        write_json_atomic(record, unit_path(cfg.out_dir, unit.scene.name, unit.views))
        return record

    def unit_fingerprint(self, key: tuple[str, int]) -> str:
        """The job's settings and restorers with the content of the unit's scene folder (not its path)."""
        return _fingerprint(self.fingerprint, names_and_bytes_digest(Path(self.source.root) / key[0]))

    def run(self, key: tuple[str, int], progress: Progress | None = None) -> dict:
        """The whole unit in this process."""
        parts = self.parts()
        task = progress.add_task(f"{key[0]} K={key[1]}", total=len(parts)) if progress else None
        cold = self.cold_start(key)
        results = {}
        for part in parts:
            results[part] = self.part(key, cold, part)
            if progress is not None:
                progress.advance(task)
        return self.finish(key, results)


_FORKED_JOB: _UnitJob | None = None  # set in the parent just before forking the worker pool


def _one_thread() -> None:
    # Tiny tensors: one intra-op thread per worker, the workers themselves use the cores.
    torch.set_num_threads(1)


def _cold_start_forked(key: tuple[str, int]) -> tuple[tuple[str, int], GaussianFitter]:
    _one_thread()
    return key, _FORKED_JOB.cold_start(key)


def _part_forked(task: tuple[tuple[str, int], GaussianFitter, str]) -> tuple[tuple[str, int], str, object]:
    _one_thread()
    key, cold, part = task
    return key, part, _FORKED_JOB.part(key, cold, part)


def _run_units(job: _UnitJob, keys: list[tuple[str, int]], workers: int, progress: Progress,
               plain: PlainProgress) -> Iterator[tuple[tuple[str, int], dict]]:
    """Run units serially, or in ``workers`` forked processes (CPU only: 3DGS optimisation of tiny scenes is
    dominated by per-op overhead that threads cannot spread). Forked, the cold starts come first, then every
    unit's parts are queued longest first, so no worker idles while another finishes a whole unit (with a
    few units, one unit per process left one core idle for a third of the run)."""
    items = 0  # cold starts and parts finished: the work the time left is measured on
    if workers <= 1 or not keys:
        for key in keys:
            yield key, job.run(key, progress if job.cfg.progress else None)
            items += 1 + len(job.parts())
            plain.update(items)
        return
    parts = job.parts()
    global _FORKED_JOB
    _FORKED_JOB = job
    try:
        with multiprocessing.get_context("fork").Pool(min(workers, len(keys) * len(parts)),
                                                      initializer=die_with_parent,
                                                      initargs=(os.getpid(),)) as pool:
            colds = {}
            for key, cold in pool.imap_unordered(_cold_start_forked, keys):
                colds[key] = cold
                items += 1
                plain.update(items)
            finished: dict[tuple[str, int], dict] = {key: {} for key in keys}
            tasks = [(key, colds[key], part) for part in parts for key in keys]
            for key, part, result in pool.imap_unordered(_part_forked, tasks):
                finished[key][part] = result
                items += 1
                plain.update(items)
                if len(finished[key]) == len(parts):
                    yield key, job.finish(key, finished.pop(key))
            # Let the workers exit on their own: the pool's __exit__ would SIGTERM them, and pycolmap's
            # signal handler then prints a stack trace for every worker.
            pool.close()
            pool.join()
    finally:
        _FORKED_JOB = None


def score_units(cfg: EvaluationConfig, source: SceneSourceConfig, refine_cfg: RefinementConfig,
                fit_cfg: GaussianFitConfig, restorers: Mapping[str, ClipRestorer | None],
                scenes: Sequence[str], gt_renderer: GroundTruthRenderer | None = None) -> dict:
    """Evaluate this shard's units (skipping finished ones) and, for an unsharded run, merge them.

    ``restorers`` maps each method to its restorer (``None`` = plain 3DGS). ``scenes`` are the test scenes as the
    run worked them out, once, held out from training (tracegs.pipeline.restorers.test_scenes). Returns the
    merged results dict when ``num_shards == 1``, else this shard's units.
    """
    unknown = [m for m in cfg.methods if m not in METHODS]
    if unknown:
        raise ValueError(f"evaluation.methods has unknown methods {unknown}; choose from {list(METHODS)}")
    require_lpips_convention(cfg.lpips_convention, "evaluation.lpips_convention")
    require_ssim_convention(cfg.ssim_convention, "evaluation.ssim_convention")
    require_lpips(cfg.lpips, cfg.require_lpips, cfg.lpips_weights)
    if cfg.workers < 1:
        raise ValueError(f"evaluation.workers must be >= 1, got {cfg.workers}")
    require_available(fit_cfg.backend, "data.prepare.fit.backend")
    scenes = list(scenes)
    if not scenes:
        raise ValueError("evaluation.scenes is empty: name the test scenes to evaluate")
    require_captioner(refine_cfg.captions, "deploy.captions")
    refine_cfg.validate()
    source = deployment_source(source, refine_cfg)
    require_writable_dir(cfg.out_dir, "evaluation.out_dir", finished_ok=True)
    restorer_ids = {m: "3dgs" if r is None else getattr(r, "identity", type(r).__name__) for m, r in restorers.items()}
    metrics = ImageMetrics(lpips=cfg.lpips, lpips_convention=cfg.lpips_convention, lpips_weights=cfg.lpips_weights,
                           ssim_convention=cfg.ssim_convention)
    # The LPIPS label says whether LPIPS was computed: a unit scored without it is scored again once it can be.
    job = _UnitJob(cfg, source, refine_cfg, fit_cfg, restorers, metrics, gt_renderer,
                   _fingerprint(refine_cfg, fit_cfg, source, restorer_ids, cfg.methods,
                                metrics.lpips_label, metrics.ssim_label))
    done: dict[tuple[str, int], dict] = {}
    todo = []
    for key in evaluation_units(scenes, cfg.views, cfg.shard_index, cfg.num_shards):
        path = unit_path(cfg.out_dir, *key)
        previous = json.loads(path.read_text()) if path.is_file() and not cfg.force else {}
        if previous.get("fingerprint") == job.unit_fingerprint(key):
            done[key] = previous
        else:
            todo.append(key)
    if done:
        log.info("evaluation: %d of %d units already finished with these settings, restorers and scenes: kept "
                 "as they are", len(done), len(done) + len(todo))
    # Forked workers must not inherit a CUDA context; GPU runs go one unit at a time.
    workers = 1 if torch.cuda.is_available() else cfg.workers
    with Progress(disable=not cfg.progress) as progress:
        overall = progress.add_task("evaluation units", total=len(todo))
        # Each unit is a cold start and its parts; forked, they run ``workers`` at a time across units.
        items = len(todo) * (1 + len(job.parts())) if todo else 0
        plain = PlainProgress("evaluation parts", items,
                              parallel=max(1, min(workers, len(todo) * len(job.parts()))))
        for key, record in _run_units(job, todo, workers, progress, plain):
            done[key] = record
            progress.advance(overall)
    if cfg.num_shards == 1:
        return merge_results(cfg.out_dir, scenes=scenes, views=cfg.views, methods=cfg.methods)
    return {f"{s}/views_{k}": u for (s, k), u in done.items()}


