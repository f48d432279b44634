"""Deployment over test scenes: the (scene, K) units and the restore-refine of each (Algorithm 1 bottom).

One *unit* is a (scene, K) pair: the scene split exactly as ``prepare`` splits it, its sparse views V_s
and the sparse-only cold start fitted from them. Units are the shards of a Hydra multirun / SLURM array
(``shard_index`` / ``num_shards``). ``deploy_scenes`` refines each unit with one restorer and saves the
3DGS; scoring the refined models is evaluation (``tracegs.eval.scoring``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from rich.progress import Progress
from torch import Tensor

from tracegs.console import PlainProgress
from tracegs.data.captions import require_captioner
from tracegs.data.colmap import Scene, load_scene
from tracegs.data.config import SceneSourceConfig
from tracegs.data.preparation.fits import MIN_INIT_POINTS
from tracegs.data.splits import split_scene
from tracegs.deploy.config import EvaluationConfig, RefinementConfig, Resolution
from tracegs.deploy.refine import cold_start, refine
from tracegs.deploy.restorers import ClipRestorer
from tracegs.io import atomic_write
from tracegs.splat.cameras import Camera
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.fit import GaussianFitter, View, random_initial_model
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.ply import save_ply
from tracegs.splat.render import render_each, require_available


def evaluation_units(scenes: Sequence[str], views: Sequence[int], shard_index: int = 0,
                     num_shards: int = 1) -> list[tuple[str, int]]:
    """The (scene, K) units of shard ``shard_index`` (round-robin, so shards get similar work)."""
    if num_shards < 1 or not 0 <= shard_index < num_shards:
        raise ValueError(f"evaluation.shard_index={shard_index} must lie in [0, num_shards={num_shards})")
    units = [(scene, int(k)) for scene in scenes for k in views]
    return units[shard_index::num_shards]

def deployment_source(source: SceneSourceConfig, cfg: RefinementConfig) -> SceneSourceConfig:
    """The scenes as deployment fits, refines and scores them: resized to ``source``'s height x width
    (``resolution=frame``), or at the dataset's own images (``resolution=dataset``, GSFixer's release), whose clips
    ``render_round_clips`` resizes to the restorer's ``clip_size``; their K-view sets by ``cfg.view_rule`` where
    it names one."""
    if cfg.resolution == Resolution.dataset:
        source = replace(source, height=None, width=None, long_side=None)
    return source if cfg.view_rule is None else replace(source, view_rule=cfg.view_rule)


def initial_model(scene: Scene, captured_ids: Sequence[int], captured: Sequence[View],
                  fit_cfg: GaussianFitConfig) -> GaussianModel:
    """3DGS initialisation exactly as ``prepare`` made the sparse fits of the training data: the SfM points
    V_s itself observes (``fit_cfg.init_min_views`` of its views), else random Gaussians where the cameras look."""
    points, colors = scene.points_seen_by(list(captured_ids), fit_cfg.init_min_views)
    if len(points) >= MIN_INIT_POINTS:
        return GaussianModel.from_points(points, colors)
    return random_initial_model(captured, fit_cfg)

@dataclass
class SceneUnit:
    """Everything deployment and scoring need for one (scene, K): V_s, its init and the test views."""

    scene: Scene
    views: int
    captured_ids: list[int]
    captured: list[View]
    test_ids: list[int]
    test_cameras: list[Camera]
    test_images: list[Tensor]  # [3,H,W] ground truth of each held-out test view, at its camera's size

    def cold_start(self, refine_cfg: RefinementConfig, fit_cfg: GaussianFitConfig) -> GaussianFitter:
        init = initial_model(self.scene, self.captured_ids, self.captured, fit_cfg)
        return cold_start(self.captured, init, refine_cfg, fit_cfg)

    def render_tests(self, model: GaussianModel, background: Tensor) -> list[Tensor]:
        """``model`` rendered at each test camera (its own size: portrait views stay portrait), on the CPU."""
        return [image.cpu() for image in render_each(model, self.test_cameras, background, None)]


def load_unit(scene: Scene, views: int, source: SceneSourceConfig) -> SceneUnit:
    """Split ``scene`` as prepare does (``split_scene``, with ``source``'s view rule: ``deployment_source`` may set
    GSFixer's) and load V_s and the test set. Test views are disjoint from every training view, so reference frames
    never enter the metrics."""
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
        test_images=[scene.load_image(i) for i in split.test],
    )

def save_model(model: GaussianModel, path: Path) -> Path:
    """The refined 3DGS as a standard 3DGS PLY, written whole or not at all."""
    with atomic_write(path) as tmp:
        save_ply(model, tmp)
    return path

def deploy_scenes(cfg: EvaluationConfig, source: SceneSourceConfig, refine_cfg: RefinementConfig,
                  fit_cfg: GaussianFitConfig, restorer: ClipRestorer | None, scenes: Sequence[str],
                  out_dir: str | Path) -> list[Path]:
    """Restore-refine this shard's (scene, K) units with one restorer and save each refined 3DGS as
    ``<out_dir>/<scene>/views_<K>.ply`` (standard 3DGS layout). Existing PLYs are kept unless ``cfg.force``.
    ``scenes`` are the test scenes as the run worked them out, once, held out from training
    (tracegs.pipeline.restorers.test_scenes)."""
    refine_cfg.validate()
    require_available(fit_cfg.backend, "data.prepare.fit.backend")
    require_captioner(refine_cfg.captions, "deploy.captions")
    written = []
    with Progress(disable=not cfg.progress) as progress:
        units = evaluation_units(scenes, cfg.views, cfg.shard_index, cfg.num_shards)
        task = progress.add_task("deploy", total=len(units))
        plain = PlainProgress("deploy", len(units))
        loaded: dict[str, Scene] = {}
        source = deployment_source(source, refine_cfg)
        for finished, (scene_name, views) in enumerate(units, 1):
            target = Path(out_dir) / scene_name / f"views_{views}.ply"
            if not target.is_file() or cfg.force:
                if scene_name not in loaded:
                    loaded[scene_name] = load_scene(source, scene_name)
                unit = load_unit(loaded[scene_name], views, source)
                model = refine(unit.cold_start(refine_cfg, fit_cfg), unit.captured, restorer, refine_cfg, fit_cfg,
                               caption=unit.scene.caption or "", seed=refine_cfg.seed)
                save_model(model, target)
            written.append(target)
            progress.advance(task)
            plain.update(finished)
    return written

