"""Evaluation over test scenes x view counts x methods (supplement B, "Metric computation").

One *unit* is a (scene, K) pair: fit the sparse-only cold start from V_s once, branch it for every
method (plain 3DGS, the baseline restorer, TRACE-GS), score each final model on the scene's test views
(never the captured/reference views), and write ``units/<scene>/views_<K>.json`` with per-view and
per-scene metrics. Units are the shards of a Hydra multirun / SLURM array (``shard_index`` /
``num_shards``); ``merge_results`` averages each scene's test views, then scenes, into ``results.json``
and the Tables 1/2 layout. Finished units are skipped on rerun unless their settings changed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import multiprocessing
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from rich.progress import Progress
from torch import Tensor

from tracegs.console import PlainProgress
from tracegs.data.captions import require_captioner
from tracegs.data.colmap import Scene, load_scene, require_held_out, training_scenes
from tracegs.data.config import SceneSourceConfig
from tracegs.data.prepare import MIN_INIT_POINTS
from tracegs.data.splits import split_scene
from tracegs.deploy.config import METHODS, EvaluationConfig, RefinementConfig
from tracegs.deploy.refine import cold_start, refine, render_round_clips
from tracegs.deploy.restorers import ClipRestorer, DiffusionRestorer
from tracegs.errors import NonFiniteError, require_writable_dir
from tracegs.eval.interval_tables import write_main_intervals, write_per_step_intervals
from tracegs.eval.metrics import LPIPS_CONVENTIONS, ImageMetrics, mean_metrics
from tracegs.eval.per_step import mean_curves, per_step_psnr
from tracegs.eval.report import (
    META_KEY,
    METHOD_LABELS,
    plot_per_step_quality,
    save_comparison_video,
    save_frames,
    save_qualitative_grid,
    write_results_tables,
)
from tracegs.io import atomic_write, write_json_atomic
from tracegs.processes import die_with_parent
from tracegs.splat.cameras import Camera
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.fit import GaussianFitter, View
from tracegs.splat.fit import initial_model as random_initial_model
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.ply import save_ply
from tracegs.splat.render import render_views, require_available
from tracegs.splat.trajectory import bridge_poses

# Ground truth at arbitrary poses, where the scene is known (the synthetic benchmark): (scene, cameras) ->
# [F,3,H,W] in [0,1]. Used for the video's GT column and the per-step (Fig. 6) curves.
GroundTruthRenderer = Callable[[Scene, Sequence[Camera]], Tensor]


def evaluation_units(scenes: Sequence[str], views: Sequence[int], shard_index: int = 0,
                     num_shards: int = 1) -> list[tuple[str, int]]:
    """The (scene, K) units of shard ``shard_index`` (round-robin, so shards get similar work)."""
    if num_shards < 1 or not 0 <= shard_index < num_shards:
        raise ValueError(f"evaluation.shard_index={shard_index} must lie in [0, num_shards={num_shards})")
    units = [(scene, int(k)) for scene in scenes for k in views]
    return units[shard_index::num_shards]


def unit_path(out_dir: str | Path, scene: str, views: int) -> Path:
    return Path(out_dir) / "units" / scene / f"views_{views}.json"


def initial_model(scene: Scene, captured_ids: Sequence[int], captured: Sequence[View],
                  fit_cfg: GaussianFitConfig) -> GaussianModel:
    """3DGS initialisation exactly as ``prepare`` made the sparse fits of the training data: the SfM points
    V_s itself observes (no leak from other views), else random Gaussians where the cameras look."""
    points, colors = scene.points_seen_by(list(captured_ids))
    if len(points) >= MIN_INIT_POINTS:
        return GaussianModel.from_points(points, colors)
    return random_initial_model(captured, fit_cfg)


def test_trajectory(cameras: Sequence[Camera], frames: int) -> list[Camera]:
    """A smooth path through the test cameras (bridges between consecutive ones) for the videos."""
    if len(cameras) < 2:
        return list(cameras) * max(frames, 1)
    per_leg = max(2, frames // (len(cameras) - 1))
    path: list[Camera] = []
    for a, b in zip(cameras, cameras[1:]):
        path.extend(bridge_poses(a, b, per_leg))
    return path[:frames]


def _fingerprint(*parts) -> str:
    """Digest of everything that changes a unit's numbers, so stale units are recomputed."""
    blob = json.dumps([dataclasses.asdict(p) if dataclasses.is_dataclass(p) else p for p in parts],
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


@dataclass
class SceneUnit:
    """Everything deployment and scoring need for one (scene, K): V_s, its init and the test views."""

    scene: Scene
    views: int
    captured_ids: list[int]
    captured: list[View]
    test_ids: list[int]
    test_cameras: list[Camera]
    test_images: Tensor  # [T,3,H,W] ground truth of the held-out test views

    def cold_start(self, refine_cfg: RefinementConfig, fit_cfg: GaussianFitConfig) -> GaussianFitter:
        init = initial_model(self.scene, self.captured_ids, self.captured, fit_cfg)
        return cold_start(self.captured, init, refine_cfg, fit_cfg)


def load_unit(scene: Scene, views: int, source: SceneSourceConfig) -> SceneUnit:
    """Split ``scene`` exactly as prepare does (``split_scene``: the same nested sets) and load V_s and the
    test set. Test views are disjoint from every training view, so reference frames never enter the metrics."""
    split = split_scene(scene, source, [views])
    captured_ids = split.views(views)
    if set(captured_ids) & set(split.test):
        raise ValueError(f"{scene.name}: test views {sorted(set(captured_ids) & set(split.test))} are captured views")
    return SceneUnit(
        scene=scene,
        views=views,
        captured_ids=captured_ids,
        captured=[View(image=scene.load_image(i), camera=scene.cameras[i]) for i in captured_ids],
        test_ids=list(split.test),
        test_cameras=[scene.cameras[i] for i in split.test],
        test_images=torch.stack([scene.load_image(i) for i in split.test]),
    )


def require_finite_metrics(per_view: Sequence[Mapping[str, float | None]], unit: str) -> None:
    """A NaN or infinite score (a NaN render, an empty image) must not be averaged into a table."""
    for index, row in enumerate(per_view):
        bad = {name: value for name, value in row.items() if value is not None and not math.isfinite(value)}
        if bad:
            raise NonFiniteError(unit, f"non-finite metrics {bad} on test view {index}; nothing was written",
                                 "check the restorer weights and the refinement settings (deploy.*)")


def evaluate_unit(unit: SceneUnit, restorers: Mapping[str, ClipRestorer | None], cfg: EvaluationConfig,
                  refine_cfg: RefinementConfig, fit_cfg: GaussianFitConfig, metrics: ImageMetrics,
                  gt_renderer: GroundTruthRenderer | None = None, progress: Progress | None = None) -> dict:
    """Deploy every method on one (scene, K) from one shared cold start and score it on the test views."""
    background = torch.tensor(fit_cfg.background, dtype=torch.float32)
    cold = unit.cold_start(refine_cfg, fit_cfg)
    caption = unit.scene.caption or ""
    result: dict = {"scene": unit.scene.name, "views": unit.views, "captured": unit.captured_ids,
                    "test": unit.test_ids, "lpips": metrics.lpips_label, "methods": {}}
    test_renders: dict[str, Tensor] = {}
    models: dict[str, GaussianModel] = {}
    task = progress.add_task(f"{unit.scene.name} K={unit.views}", total=len(cfg.methods)) if progress else None
    for method in cfg.methods:
        if method not in restorers:
            raise ValueError(f"evaluation.methods lists {method!r} but no restorer was built for it")
        model = refine(cold, unit.captured, restorers[method], refine_cfg, fit_cfg, caption=caption,
                       seed=refine_cfg.seed)
        renders = render_views(model, unit.test_cameras, background, None).cpu()
        per_view = metrics.per_view(renders, unit.test_images)
        require_finite_metrics(per_view, f"scene {unit.scene.name}, {unit.views} views, method {method}")
        result["methods"][method] = {"per_view": per_view, "mean": mean_metrics(per_view)}
        test_renders[method], models[method] = renders, model
        if progress is not None:
            progress.advance(task)
    if cfg.per_step and gt_renderer is not None:
        result["per_step"] = unit_per_step_curves(unit, cold, restorers, refine_cfg, fit_cfg, gt_renderer)
    if cfg.save_media:
        result["media"] = _save_media(unit, cfg, test_renders, models, background, gt_renderer)
    if cfg.save_models:
        result["models"] = {method: str(_save_model(model, model_path(cfg.out_dir, unit.scene.name, unit.views,
                                                                           method)))
                            for method, model in models.items()}
    return result


def model_path(out_dir: str | Path, scene: str, views: int, method: str) -> Path:
    return Path(out_dir) / "models" / scene / f"views_{views}_{method}.ply"


def _save_model(model: GaussianModel, path: Path) -> Path:
    """The refined 3DGS as a standard 3DGS PLY, written whole or not at all."""
    with atomic_write(path) as tmp:
        save_ply(model, tmp)
    return path


def unit_per_step_curves(unit: SceneUnit, cold: GaussianFitter, restorers: Mapping[str, ClipRestorer | None],
                         refine_cfg: RefinementConfig, fit_cfg: GaussianFitConfig,
                         gt_renderer: GroundTruthRenderer) -> dict[str, list[float]]:
    """Fig. 6 on this unit: the first round's clips rendered from the cold start (before refinement),
    restored by each diffusion restorer, scored against ground truth at every reverse step."""
    generator = torch.Generator().manual_seed(refine_cfg.seed)
    caption = unit.scene.caption or ""
    clips = render_round_clips(cold, unit.captured, 0, refine_cfg, fit_cfg, caption, generator)
    truth = torch.stack([gt_renderer(unit.scene, clip.cameras) for clip in clips])
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


@dataclass
class _UnitJob:
    """Everything one evaluation unit needs; handed to worker processes by fork, never pickled."""

    cfg: EvaluationConfig
    source: SceneSourceConfig
    refine_cfg: RefinementConfig
    fit_cfg: GaussianFitConfig
    restorers: Mapping[str, ClipRestorer | None]
    metrics: ImageMetrics
    gt_renderer: GroundTruthRenderer | None
    fingerprint: str

    def run(self, key: tuple[str, int], progress: Progress | None = None) -> dict:
        scene_name, views = key
        unit = load_unit(load_scene(self.source, scene_name), views, self.source)
        record = evaluate_unit(unit, self.restorers, self.cfg, self.refine_cfg, self.fit_cfg, self.metrics,
                               self.gt_renderer, progress)
        record["fingerprint"] = self.fingerprint
        record["variant"] = self.cfg.variant
        write_json_atomic(record, unit_path(self.cfg.out_dir, scene_name, views))
        return record


_FORKED_JOB: _UnitJob | None = None  # set in the parent just before forking the worker pool


def _run_forked(key: tuple[str, int]) -> tuple[tuple[str, int], dict]:
    # Tiny tensors: one intra-op thread per worker, the workers themselves use the cores.
    torch.set_num_threads(1)
    return key, _FORKED_JOB.run(key)


def _run_units(job: _UnitJob, keys: list[tuple[str, int]], workers: int,
               progress: Progress) -> Iterator[tuple[tuple[str, int], dict]]:
    """Run units serially, or in ``workers`` forked processes (CPU only: the units are independent and
    3DGS optimisation of tiny scenes is dominated by per-op overhead that threads cannot spread)."""
    if workers <= 1 or len(keys) <= 1:
        for key in keys:
            yield key, job.run(key, progress if job.cfg.progress else None)
        return
    global _FORKED_JOB
    _FORKED_JOB = job
    try:
        with multiprocessing.get_context("fork").Pool(min(workers, len(keys)), initializer=die_with_parent,
                                                      initargs=(os.getpid(),)) as pool:
            yield from pool.imap_unordered(_run_forked, keys)
            # Let the workers exit on their own: the pool's __exit__ would SIGTERM them, and pycolmap's
            # signal handler then prints a stack trace for every worker.
            pool.close()
            pool.join()
    finally:
        _FORKED_JOB = None


def evaluate(cfg: EvaluationConfig, source: SceneSourceConfig, refine_cfg: RefinementConfig,
             fit_cfg: GaussianFitConfig, restorers: Mapping[str, ClipRestorer | None],
             scenes: Sequence[str] | None = None, gt_renderer: GroundTruthRenderer | None = None) -> dict:
    """Evaluate this shard's units (skipping finished ones) and, for an unsharded run, merge them.

    ``restorers`` maps each method to its restorer (``None`` = plain 3DGS). ``scenes`` defaults to
    ``cfg.scenes``. Returns the merged results dict when ``num_shards == 1``, else this shard's units.
    """
    unknown = [m for m in cfg.methods if m not in METHODS]
    if unknown:
        raise ValueError(f"evaluation.methods has unknown methods {unknown}; choose from {list(METHODS)}")
    if cfg.lpips_convention not in LPIPS_CONVENTIONS:
        raise ValueError(f"evaluation.lpips_convention must be one of {sorted(LPIPS_CONVENTIONS)}")
    if cfg.workers < 1:
        raise ValueError(f"evaluation.workers must be >= 1, got {cfg.workers}")
    require_available(fit_cfg.backend, "data.prepare.fit.backend")
    scenes = list(cfg.scenes if cfg.scenes is not None else (scenes or []))
    if not scenes:
        raise ValueError("evaluation.scenes is empty: name the test scenes to evaluate")
    require_held_out(scenes, training_scenes(source), "evaluation.scenes")
    require_captioner(refine_cfg.captions, "deploy.captions")
    refine_cfg.validate()
    require_writable_dir(cfg.out_dir, "evaluation.out_dir")
    restorer_ids = {m: "3dgs" if r is None else getattr(r, "identity", type(r).__name__) for m, r in restorers.items()}
    job = _UnitJob(cfg, source, refine_cfg, fit_cfg, restorers,
                   ImageMetrics(lpips=cfg.lpips, lpips_convention=cfg.lpips_convention), gt_renderer,
                   _fingerprint(refine_cfg, fit_cfg, source, restorer_ids, cfg.methods, cfg.lpips_convention))
    done: dict[tuple[str, int], dict] = {}
    todo = []
    for key in evaluation_units(scenes, cfg.views, cfg.shard_index, cfg.num_shards):
        path = unit_path(cfg.out_dir, *key)
        previous = json.loads(path.read_text()) if path.is_file() and not cfg.force else {}
        if previous.get("fingerprint") == job.fingerprint:
            done[key] = previous
        else:
            todo.append(key)
    # Forked workers must not inherit a CUDA context; GPU runs go one unit at a time.
    workers = 1 if torch.cuda.is_available() else cfg.workers
    with Progress(disable=not cfg.progress) as progress:
        overall = progress.add_task("evaluation units", total=len(todo))
        plain = PlainProgress("evaluation units", len(todo))
        for finished, (key, record) in enumerate(_run_units(job, todo, workers, progress), 1):
            done[key] = record
            progress.advance(overall)
            plain.update(finished)
    if cfg.num_shards == 1:
        return merge_results(cfg.out_dir, scenes=scenes, views=cfg.views, methods=cfg.methods)
    return {f"{s}/views_{k}": u for (s, k), u in done.items()}


def merge_results(out_dir: str | Path, scenes: Sequence[str] | None = None, views: Sequence[int] | None = None,
                  methods: Sequence[str] | None = None) -> dict:
    """Merge unit files (from one or many shards) into ``results.json``, ``per_scene.json`` and the table.

    Each (method, K) cell is the unweighted mean over scenes of the per-scene means over test views.
    Every requested scene must have a unit for every requested K, so no cell silently averages fewer
    scenes than another. ``None`` selects whatever units exist.
    """
    out_dir = Path(out_dir)
    files = sorted((out_dir / "units").glob("*/views_*.json"))
    if not files:
        raise FileNotFoundError(f"no evaluation units under {out_dir / 'units'}")
    units = [json.loads(f.read_text()) for f in files]
    scenes = sorted({u["scene"] for u in units}) if scenes is None else list(scenes)
    views = sorted({int(u["views"]) for u in units}) if views is None else [int(v) for v in views]
    by_key = {(u["scene"], int(u["views"])): u for u in units}
    missing = [f"{s}/views_{k}" for s in scenes for k in views if (s, k) not in by_key]
    if missing:
        raise FileNotFoundError(f"{out_dir / 'units'}: missing evaluation units {missing} (shards not finished?)")
    chosen = [by_key[(s, k)] for s in scenes for k in views]
    if methods is None:
        methods = [m for m in METHODS if all(m in u["methods"] for u in chosen)]
    lpips_labels = sorted({u["lpips"] for u in chosen})
    variants = sorted({u.get("variant") for u in chosen}, key=str)
    results: dict = {}
    per_scene: dict = {s: {} for s in scenes}
    for method in methods:
        results[method] = {}
        for k in views:
            scene_means = [by_key[(s, k)]["methods"][method]["mean"] for s in scenes]
            results[method][str(k)] = mean_metrics(scene_means)
            for s, mean in zip(scenes, scene_means):
                per_scene[s].setdefault(method, {})[str(k)] = mean
    results[META_KEY] = {
        "lpips": "; ".join(lpips_labels),
        "scenes": list(scenes),
        "variant": variants[0] if len(variants) == 1 else variants,
        "protocol": "mean over each scene's test views (captured views excluded), then unweighted mean over scenes",
    }
    write_json_atomic(results, out_dir / "results.json")
    write_json_atomic(per_scene, out_dir / "per_scene.json")
    unit_curves = {(u["scene"], str(u["views"])): u["per_step"] for u in chosen if u.get("per_step")}
    if unit_curves:
        # Fig. 6 protocol: averaged across view settings (and scenes), before 3DGS refinement.
        mean = mean_curves(list(unit_curves.values()))
        write_json_atomic(mean, out_dir / "per_step.json")
        bands = write_per_step_intervals(unit_curves, out_dir, "per_step", pairs=[("tracegs", "baseline")])
        plot_per_step_quality({METHOD_LABELS.get(m, m): c for m, c in mean.items()}, out_dir / "fig6_per_step.png",
                              bands={METHOD_LABELS.get(m, m): band for m, band in bands.items()})
    write_results_tables(results, out_dir, stem="table", views=[str(k) for k in views])
    write_main_intervals(per_scene, out_dir, [str(k) for k in views])
    return results


def deploy_scenes(cfg: EvaluationConfig, source: SceneSourceConfig, refine_cfg: RefinementConfig,
                  fit_cfg: GaussianFitConfig, restorer: ClipRestorer | None, scenes: Sequence[str],
                  out_dir: str | Path) -> list[Path]:
    """Restore-refine this shard's (scene, K) units with one restorer and save each refined 3DGS as
    ``<out_dir>/<scene>/views_<K>.ply`` (standard 3DGS layout). Existing PLYs are kept unless ``cfg.force``."""
    refine_cfg.validate()
    require_available(fit_cfg.backend, "data.prepare.fit.backend")
    scenes = list(cfg.scenes if cfg.scenes is not None else scenes)
    require_held_out(scenes, training_scenes(source), "evaluation.scenes")
    require_captioner(refine_cfg.captions, "deploy.captions")
    written = []
    with Progress(disable=not cfg.progress) as progress:
        units = evaluation_units(scenes, cfg.views, cfg.shard_index, cfg.num_shards)
        task = progress.add_task("deploy", total=len(units))
        plain = PlainProgress("deploy", len(units))
        loaded: dict[str, Scene] = {}
        for finished, (scene_name, views) in enumerate(units, 1):
            target = Path(out_dir) / scene_name / f"views_{views}.ply"
            if not target.is_file() or cfg.force:
                if scene_name not in loaded:
                    loaded[scene_name] = load_scene(source, scene_name)
                unit = load_unit(loaded[scene_name], views, source)
                model = refine(unit.cold_start(refine_cfg, fit_cfg), unit.captured, restorer, refine_cfg, fit_cfg,
                               caption=unit.scene.caption or "", seed=refine_cfg.seed)
                _save_model(model, target)
            written.append(target)
            progress.advance(task)
            plain.update(finished)
    return written
