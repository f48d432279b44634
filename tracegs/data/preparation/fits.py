"""The 3DGS fits of a preparation (supplement A.2): one resumable work unit per (scene, view set), its
snapshots saved as PLY in a folder named by the fit settings, and the condition each snapshot renders.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from rich.progress import Progress

from tracegs.console import PlainProgress
from tracegs.data.cache_keys import condition_key
from tracegs.data.config import PrepareConfig
from tracegs.data.preparation.plan import ScenePlan, settings_digest
from tracegs.io import atomic_write
from tracegs.processes import WorkerPool, run_units
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.fit import View, fit_gaussians
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.ply import save_ply

MIN_INIT_POINTS = 64  # fewer triangulated points than this: initialise the fit randomly instead


def fit_unit_paths(work_dir: Path, scene: str, key: str, snapshots: list[int], fit: GaussianFitConfig
                   ) -> dict[int, Path]:
    """PLY per snapshot of one (scene, view set) fit, in a directory named by the fit settings."""
    unit = work_dir / scene / f"fit_{key}_{settings_digest(asdict(fit))}"
    return {it: unit / f"it{it:06d}.ply" for it in snapshots}


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
