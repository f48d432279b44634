"""End-to-end evaluation on a tiny synthetic scene written to disk in COLMAP format: results.json layout,
media, per-step curves, resumable and sharded units, a rerun after SIGKILL, plain progress lines; and the
Lightning callback logging deployment metrics.

Restorers: ``tracegs`` is the ground-truth oracle (``GroundTruthRestorer`` on the scene's true Gaussians),
``baseline`` the real diffusion pipeline of a randomly initialised tiny backbone (2 reverse steps), so
every code path runs without trained weights.
"""

import json
import logging
import os
import random
import signal
import time
from pathlib import Path

import lightning as L
import pytest
import torch
from torch import nn
from vgg16_layout import write_vgg16_weights

from tracegs.data.colmap import load_scene
from tracegs.data.config import SceneSourceConfig, SyntheticConfig
from tracegs.data.synthetic import generate_scene, ground_truth_model, render_ground_truth, scene_name
from tracegs.deploy.config import EvaluationConfig, RefinementConfig
from tracegs.deploy.restorers import DiffusionRestorer, GroundTruthRestorer
from tracegs.deploy.scenes import deploy_scenes
from tracegs.eval.callback import DeploymentRefinement, module_restorer_factory
from tracegs.eval.evaluate import evaluate
from tracegs.eval.merge import merge_results, unit_path
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig
from tracegs.restorer.sampler import RestorationPipeline
from tracegs.splat.config import DensificationConfig, GaussianFitConfig, TrajectoryConfig
from tracegs.splat.ply import load_ply

SEED = 100


@pytest.fixture(scope="module")
def scene_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    cfg = SyntheticConfig(root=str(root), num_views=16, height=24, width=32, num_objects=1,
                          gaussians_per_unit_area=150, init_points=400)
    generate_scene(SEED, cfg, root)
    return root


@pytest.fixture(scope="module")
def backbone():
    return build_backbone(BackboneConfig())


def _configs():
    fit_cfg = GaussianFitConfig(iterations=40, snapshot_iters=[], densification=DensificationConfig(enabled=False))
    refine_cfg = RefinementConfig(total_iters=40, repair_iters=[10, 25],
                                  trajectory=TrajectoryConfig(frames_per_clip=9, ellipse_frames=24),
                                  max_clips_per_round=1, steps=2)
    return fit_cfg, refine_cfg


def test_evaluate_writes_results_media_and_resumes(scene_root, backbone, tmp_path):
    source = SceneSourceConfig(root=str(scene_root))
    scene = load_scene(source, scene_name(SEED))
    fit_cfg, refine_cfg = _configs()
    restorers = {
        "3dgs": None,
        "baseline": DiffusionRestorer(RestorationPipeline(backbone), batch=2, identity="random tiny", steps=2),
        "tracegs": GroundTruthRestorer(ground_truth_model(scene)),
    }
    cfg = EvaluationConfig(out_dir=str(tmp_path / "eval"), views=[3], grid_views=2, video_frames=6,
                           progress=False, variant="F")
    results = evaluate(cfg, source, refine_cfg, fit_cfg, restorers, scenes=[scene.name],
                       gt_renderer=render_ground_truth)

    on_disk = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert on_disk == json.loads(json.dumps(results))
    for method in ("3dgs", "baseline", "tracegs"):
        cell = on_disk[method]["3"]
        assert set(cell) == {"psnr", "ssim", "lpips"}
        assert 5.0 < cell["psnr"] < 60.0 and 0.0 < cell["ssim"] <= 1.0
    assert on_disk["meta"]["variant"] == "F" and on_disk["meta"]["scenes"] == [scene.name]

    unit_file = unit_path(cfg.out_dir, scene.name, 3)
    unit = json.loads(unit_file.read_text())
    assert unit["test"] == [0, 8] and not set(unit["test"]) & set(unit["captured"])  # every-8th test views
    assert len(unit["methods"]["3dgs"]["per_view"]) == 2
    assert set(unit["per_step"]) == {"baseline"} and len(unit["per_step"]["baseline"]) == 2
    # named relative to the evaluation folder, which can then be copied or moved
    out = Path(cfg.out_dir)
    assert (out / unit["media"]["grid"]).is_file() and (out / unit["media"]["video"]).is_file()
    assert not Path(unit["media"]["grid"]).is_absolute()
    assert (tmp_path / "eval" / "fig6_per_step.png").is_file() and (tmp_path / "eval" / "table.md").is_file()

    # a rerun with the same settings skips the finished unit; a changed restorer recomputes it
    stamp = unit_file.stat().st_mtime_ns
    evaluate(cfg, source, refine_cfg, fit_cfg, restorers, scenes=[scene.name])
    assert unit_file.stat().st_mtime_ns == stamp
    restorers["baseline"].identity = "retrained"
    cfg.save_media = cfg.per_step = False
    evaluate(cfg, source, refine_cfg, fit_cfg, {"3dgs": None, **{k: restorers[k] for k in ("baseline", "tracegs")}},
             scenes=[scene.name])
    assert unit_file.stat().st_mtime_ns != stamp


def test_a_unit_scored_without_lpips_is_scored_again_once_it_can_be(scene_root, tmp_path):
    """LPIPS availability is part of a unit's identity: putting the VGG16 file in place later fills the column."""
    source = SceneSourceConfig(root=str(scene_root))
    fit_cfg, refine_cfg = _configs()
    weights = tmp_path / "vgg16-397923af.pth"
    cfg = EvaluationConfig(out_dir=str(tmp_path / "eval"), views=[3], methods=["3dgs"], lpips_weights=str(weights),
                           save_media=False, per_step=False, progress=False, workers=1)
    first = evaluate(cfg, source, refine_cfg, fit_cfg, {"3dgs": None}, scenes=[scene_name(SEED)])
    assert first["3dgs"]["3"]["lpips"] is None and "not found" in first["meta"]["lpips"]
    write_vgg16_weights(weights)
    again = evaluate(cfg, source, refine_cfg, fit_cfg, {"3dgs": None}, scenes=[scene_name(SEED)])
    assert isinstance(again["3dgs"]["3"]["lpips"], float) and again["meta"]["lpips"].startswith("LPIPS-VGG")
    assert again["3dgs"]["3"]["psnr"] == first["3dgs"]["3"]["psnr"]  # the same fit, now with its LPIPS


def test_sharded_and_parallel_evaluation_agree(scene_root, tmp_path):
    source = SceneSourceConfig(root=str(scene_root))
    fit_cfg, refine_cfg = _configs()
    name = scene_name(SEED)
    for shard in (0, 1):
        cfg = EvaluationConfig(out_dir=str(tmp_path / "sharded"), methods=["3dgs"], views=[3, 4],
                               shard_index=shard, num_shards=2, save_media=False, progress=False)
        units = evaluate(cfg, source, refine_cfg, fit_cfg, {"3dgs": None}, scenes=[name])
        assert list(units) == [f"{name}/views_{3 + shard}"]
    assert not (tmp_path / "sharded" / "results.json").exists()
    merged = merge_results(tmp_path / "sharded", views=[3, 4], methods=["3dgs"])
    # the same two units in one run, evaluated by two forked worker processes
    cfg = EvaluationConfig(out_dir=str(tmp_path / "parallel"), methods=["3dgs"], views=[3, 4], workers=2,
                           save_media=False, progress=False)
    parallel = evaluate(cfg, source, refine_cfg, fit_cfg, {"3dgs": None}, scenes=[name])
    for k in ("3", "4"):
        assert parallel["3dgs"][k]["psnr"] == pytest.approx(merged["3dgs"][k]["psnr"], abs=1e-4)


def test_forked_evaluation_splits_a_unit_into_its_methods(scene_root, tmp_path):
    """Two worker processes share one unit's methods (from one cold start): each method keeps its own scores,
    in the configured order, as when the unit runs in one process."""
    source = SceneSourceConfig(root=str(scene_root))
    fit_cfg, refine_cfg = _configs()
    scene = load_scene(source, scene_name(SEED))
    restorers = {"3dgs": None, "tracegs": GroundTruthRestorer(ground_truth_model(scene))}
    units = {}
    for workers in (1, 2):
        cfg = EvaluationConfig(out_dir=str(tmp_path / f"workers{workers}"), methods=["3dgs", "tracegs"], views=[3],
                               workers=workers, save_media=False, progress=False)
        evaluate(cfg, source, refine_cfg, fit_cfg, restorers, scenes=[scene.name])
        units[workers] = json.loads(unit_path(cfg.out_dir, scene.name, 3).read_text())
    assert list(units[2]["methods"]) == ["3dgs", "tracegs"]
    for method in ("3dgs", "tracegs"):
        serial, forked = (units[w]["methods"][method]["mean"]["psnr"] for w in (1, 2))
        assert forked == pytest.approx(serial, abs=1e-4)
    # the two methods score differently, so a swapped or duplicated part would fail the comparison above
    scores = [units[2]["methods"][m]["mean"]["psnr"] for m in ("3dgs", "tracegs")]
    assert abs(scores[0] - scores[1]) > 1e-3


class _TinyRestorerModule(L.LightningModule):
    """A training module around the restorer's transformer (what the callback deploys) with one
    trainable scalar so Lightning has something to optimise."""

    def __init__(self, transformer):
        super().__init__()
        self.transformer = transformer
        self.scale = nn.Parameter(torch.ones(()))

    def training_step(self, batch, batch_idx):
        return (self.scale * batch[0]).square().mean()

    def validation_step(self, batch, batch_idx):
        self.log("val_loss", (self.scale * batch[0]).square().mean())

    def configure_optimizers(self):
        return torch.optim.SGD([self.scale], lr=0.1)


def test_callback_deploys_the_module_restorer_and_logs(scene_root, backbone, tmp_path):
    source = SceneSourceConfig(root=str(scene_root))
    fit_cfg, refine_cfg = _configs()
    callback = DeploymentRefinement([scene_name(SEED)], source, module_restorer_factory(backbone, None, steps=1),
                                    refine_cfg, fit_cfg, views=[3], every_n_epochs=1)
    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.ones(2, 1)), batch_size=2)
    trainer = L.Trainer(max_epochs=1, callbacks=[callback], logger=L.pytorch.loggers.CSVLogger(tmp_path),
                        enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0,
                        enable_checkpointing=False, accelerator="cpu")
    module = _TinyRestorerModule(backbone.transformer)
    trainer.fit(module, data, data)
    assert len(callback.history) == 1
    assert "deploy/psnr_k3" in trainer.callback_metrics and "deploy/ssim_k3" in trainer.callback_metrics
    assert 5.0 < float(trainer.callback_metrics["deploy/psnr_k3"]) < 60.0
    assert ("deploy/lpips_k3" in trainer.callback_metrics) == callback.metrics.lpips_status.available
    # the logger received the deployment metrics too
    logged = (Path(trainer.logger.log_dir) / "metrics.csv").read_text().splitlines()[0]
    assert "deploy/psnr_k3" in logged


def test_deploy_scenes_writes_refined_ply_once(scene_root, tmp_path):
    source = SceneSourceConfig(root=str(scene_root))
    fit_cfg, refine_cfg = _configs()
    cfg = EvaluationConfig(views=[3], progress=False)
    oracle = GroundTruthRestorer(ground_truth_model(load_scene(source, scene_name(SEED))))
    (path,) = deploy_scenes(cfg, source, refine_cfg, fit_cfg, oracle, [scene_name(SEED)], tmp_path)
    assert path == tmp_path / scene_name(SEED) / "views_3.ply"
    assert len(load_ply(path)) > 0
    stamp = path.stat().st_mtime_ns
    deploy_scenes(cfg, source, refine_cfg, fit_cfg, oracle, [scene_name(SEED)], tmp_path)
    assert path.stat().st_mtime_ns == stamp  # finished scenes are kept


def _plain_3dgs_runs(source: SceneSourceConfig, views: tuple[int, ...] = (3, 4)):
    """Evaluation and deployment of plain 3DGS (no restorer) on ``views``, ``out -> None`` each."""
    fit_cfg, refine_cfg = _configs()
    names = [scene_name(SEED)]

    def cfg(out: Path) -> EvaluationConfig:
        return EvaluationConfig(out_dir=str(out), methods=["3dgs"], views=list(views), workers=1,
                                save_media=False, per_step=False, progress=False)

    return {
        "evaluate": lambda out: evaluate(cfg(out), source, refine_cfg, fit_cfg, {"3dgs": None}, scenes=names),
        "deploy": lambda out: deploy_scenes(cfg(out), source, refine_cfg, fit_cfg, None, names, out),
    }


def _products(stage: str, out: Path) -> dict[str, bytes]:
    """What a finished stage leaves: evaluation's results and unit files, deployment's PLYs."""
    pattern = "units/*/views_*.json" if stage == "evaluate" else "*/views_*.ply"
    found = {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.glob(pattern))}
    if (out / "results.json").is_file():
        found["results.json"] = (out / "results.json").read_bytes()
    return found


@pytest.fixture(scope="module")
def uninterrupted(scene_root, tmp_path_factory):
    """Each stage's products of an uninterrupted run."""
    tmp = tmp_path_factory.mktemp("uninterrupted")
    runs = _plain_3dgs_runs(SceneSourceConfig(root=str(scene_root)))
    for stage, run in runs.items():
        run(tmp / stage)
    return {stage: _products(stage, tmp / stage) for stage in runs}


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)])
@pytest.mark.parametrize("stage", ["evaluate", "deploy"])
def test_killed_run_reruns_to_the_same_products(scene_root, uninterrupted, forked, tmp_path, stage, seed):
    """SIGKILL after a random number of finished units plus a random delay (seeded), then the same call: the
    results / PLYs equal the uninterrupted run's byte for byte, and finished units are not redone."""
    run = _plain_3dgs_runs(SceneSourceConfig(root=str(scene_root)))[stage]
    out = tmp_path / stage
    rng = random.Random(seed)
    kill_after, delay = rng.randrange(2), rng.uniform(0.0, 0.3)
    pid = forked(lambda: run(out), tmp_path / "stdout", tmp_path / "stderr")
    deadline = time.monotonic() + 300
    while len(_products(stage, out)) < kill_after and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(delay)
    exited, _ = os.waitpid(pid, os.WNOHANG)
    assert not exited, f"{stage} ended before it could be killed: {(tmp_path / 'stderr').read_text()[-2000:]}"
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    finished = {p: p.stat().st_mtime_ns for p in out.rglob("views_*") if not p.name.startswith(".")}
    run(out)
    assert _products(stage, out) == uninterrupted[stage]
    assert all(p.stat().st_mtime_ns == t for p, t in finished.items()), "a finished unit was redone"


def test_evaluation_and_deployment_log_plain_progress(scene_root, tmp_path, caplog, monkeypatch):
    """With stdout not a terminal (a log file, SLURM output) each loop logs a plain line at its end."""
    monkeypatch.setattr("sys.stdout.isatty", lambda: False)
    runs = _plain_3dgs_runs(SceneSourceConfig(root=str(scene_root)), views=(3,))
    with caplog.at_level(logging.INFO, logger="tracegs"):
        for stage, run in runs.items():
            run(tmp_path / stage)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith(("evaluation parts:", "deploy:"))]
    # Evaluation counts the unit's cold start and its one part (plain 3DGS), which run in parallel across units.
    assert [line.split(",")[0] for line in lines] == ["evaluation parts: 2/2", "deploy: 1/1"]
