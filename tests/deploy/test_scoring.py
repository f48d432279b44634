"""End-to-end evaluation on a tiny synthetic scene written to disk in COLMAP format: results.json layout,
media, per-step curves, resumable and sharded units, a rerun after SIGKILL, plain progress lines; and the
Lightning callback logging deployment metrics during training.

Restorers: ``tracegs`` is the ground-truth oracle (``GroundTruthRestorer`` on the scene's true Gaussians),
``baseline`` the real diffusion pipeline of a randomly initialised tiny backbone (2 reverse steps), so
every code path runs without trained weights.
"""

import csv
import json
from pathlib import Path

import lightning as L
import pytest
import torch
from support.vgg16_layout import write_vgg16_weights
from torch import nn

from tracegs.data.colmap import load_scene
from tracegs.data.config import SceneSourceConfig, SyntheticConfig
from tracegs.data.synthetic import generate_scene, ground_truth_model, render_ground_truth, scene_name
from tracegs.deploy.config import EvaluationConfig, RefinementConfig
from tracegs.deploy.restorers import DiffusionRestorer, GroundTruthRestorer
from tracegs.eval.callback import DeploymentRefinement, ModuleRestorerFactory
from tracegs.eval.merge import merge_results, unit_path
from tracegs.eval.scoring import score_units
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig
from tracegs.restorer.sampler import RestorationPipeline
from tracegs.splat.config import DensificationConfig, GaussianFitConfig, TrajectoryConfig
from tracegs.training.strategy import one_job_of_processes

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


def test_score_units_writes_results_media_and_resumes(scene_root, backbone, tmp_path):
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
    results = score_units(cfg, source, refine_cfg, fit_cfg, restorers, scenes=[scene.name],
                          gt_renderer=render_ground_truth)

    on_disk = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert on_disk == json.loads(json.dumps(results))
    for method in ("3dgs", "baseline", "tracegs"):
        cell = on_disk[method]["3"]
        assert set(cell) == {"psnr", "ssim", "ssim_alt", "lpips"}  # SSIM under both conventions (SSIM′)
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
    score_units(cfg, source, refine_cfg, fit_cfg, restorers, scenes=[scene.name])
    assert unit_file.stat().st_mtime_ns == stamp
    restorers["baseline"].identity = "retrained"
    cfg.save_media = cfg.per_step = False
    score_units(cfg, source, refine_cfg, fit_cfg, {"3dgs": None, **{k: restorers[k] for k in ("baseline", "tracegs")}},
                scenes=[scene.name])
    assert unit_file.stat().st_mtime_ns != stamp


def test_a_unit_scored_without_lpips_is_scored_again_once_it_can_be(scene_root, tmp_path):
    """LPIPS availability is part of a unit's identity: putting the VGG16 file in place later fills the column."""
    source = SceneSourceConfig(root=str(scene_root))
    fit_cfg, refine_cfg = _configs()
    weights = tmp_path / "vgg16-397923af.pth"
    cfg = EvaluationConfig(out_dir=str(tmp_path / "eval"), views=[3], methods=["3dgs"], lpips_weights=str(weights),
                           save_media=False, per_step=False, progress=False, workers=1)
    first = score_units(cfg, source, refine_cfg, fit_cfg, {"3dgs": None}, scenes=[scene_name(SEED)])
    assert first["3dgs"]["3"]["lpips"] is None and "not found" in first["meta"]["lpips"]
    write_vgg16_weights(weights)
    again = score_units(cfg, source, refine_cfg, fit_cfg, {"3dgs": None}, scenes=[scene_name(SEED)])
    assert isinstance(again["3dgs"]["3"]["lpips"], float) and again["meta"]["lpips"].startswith("LPIPS-VGG")
    assert again["3dgs"]["3"]["psnr"] == first["3dgs"]["3"]["psnr"]  # the same fit, now with its LPIPS


def test_sharded_and_parallel_evaluation_agree(scene_root, tmp_path):
    """Evaluation jobs of one GPU each (paper scale: ``evaluation.workers=1``) shard the units; their merged table
    is the one-process table bit for bit, and the forked two-worker run agrees to float rounding."""
    source = SceneSourceConfig(root=str(scene_root))
    fit_cfg, refine_cfg = _configs()
    name = scene_name(SEED)
    for shard in (0, 1):
        cfg = EvaluationConfig(out_dir=str(tmp_path / "sharded"), methods=["3dgs"], views=[3, 4], workers=1,
                               shard_index=shard, num_shards=2, save_media=False, progress=False)
        units = score_units(cfg, source, refine_cfg, fit_cfg, {"3dgs": None}, scenes=[name])
        assert list(units) == [f"{name}/views_{3 + shard}"]
    assert not (tmp_path / "sharded" / "results.json").exists()
    merged = merge_results(tmp_path / "sharded", views=[3, 4], methods=["3dgs"])
    one = EvaluationConfig(out_dir=str(tmp_path / "one"), methods=["3dgs"], views=[3, 4], workers=1,
                           save_media=False, progress=False)
    score_units(one, source, refine_cfg, fit_cfg, {"3dgs": None}, scenes=[name])
    whole = merge_results(tmp_path / "one", views=[3, 4], methods=["3dgs"])
    assert {k: merged["3dgs"][k] for k in ("3", "4")} == {k: whole["3dgs"][k] for k in ("3", "4")}
    # the same two units in one run, evaluated by two forked worker processes
    cfg = EvaluationConfig(out_dir=str(tmp_path / "parallel"), methods=["3dgs"], views=[3, 4], workers=2,
                           save_media=False, progress=False)
    parallel = score_units(cfg, source, refine_cfg, fit_cfg, {"3dgs": None}, scenes=[name])
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
        score_units(cfg, source, refine_cfg, fit_cfg, restorers, scenes=[scene.name])
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

    def configure_optimizers(self):
        return torch.optim.SGD([self.scale], lr=0.1)


def test_callback_deploys_the_module_restorer_every_k_steps_and_at_the_end(scene_root, backbone, tmp_path):
    source = SceneSourceConfig(root=str(scene_root))
    fit_cfg, refine_cfg = _configs()
    callback = DeploymentRefinement([scene_name(SEED)], source, ModuleRestorerFactory(backbone, None, steps=1),
                                    refine_cfg, fit_cfg, views=[3], every_n_steps=2)
    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.ones(2, 1)), batch_size=1)
    trainer = L.Trainer(max_steps=3, callbacks=[callback], logger=L.pytorch.loggers.CSVLogger(tmp_path),
                        enable_progress_bar=False, enable_model_summary=False, enable_checkpointing=False,
                        accelerator="cpu")
    module = _TinyRestorerModule(backbone.transformer)
    trainer.fit(module, data)
    # at step 2 (every 2 steps) and at the end (step 3)
    assert [entry["step"] for entry in callback.history] == [2, 3]
    for entry in callback.history:
        assert 5.0 < entry["deploy/psnr_k3"] < 60.0 and 0.0 < entry["deploy/ssim_k3"] <= 1.0
        assert "deploy/lpips_k3" not in entry  # LPIPS is off unless asked for
    # the logger received the deployment metrics at their steps
    with open(Path(trainer.logger.log_dir) / "metrics.csv") as handle:
        rows = [row for row in csv.DictReader(handle) if row.get("deploy/psnr_k3")]
    assert [int(row["step"]) for row in rows] == [2, 3]
    assert [float(row["deploy/psnr_k3"]) for row in rows] == pytest.approx(
        [entry["deploy/psnr_k3"] for entry in callback.history])


@pytest.mark.slow
def test_callback_under_ddp_deploys_on_rank_zero_and_training_continues(scene_root, backbone, tmp_path):
    """Two gloo ranks: rank 0 deploys and logs while rank 1 waits at the barrier, at every step and at the end,
    and both finish (no rank is left waiting)."""
    source = SceneSourceConfig(root=str(scene_root))
    fit_cfg, refine_cfg = _configs()
    callback = DeploymentRefinement([scene_name(SEED)], source, ModuleRestorerFactory(backbone, None, steps=1),
                                    refine_cfg, fit_cfg, views=[3], every_n_steps=1)
    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.ones(4, 1)), batch_size=1)
    trainer = L.Trainer(max_steps=2, devices=2, strategy="ddp_spawn", callbacks=[callback],
                        logger=L.pytorch.loggers.CSVLogger(tmp_path), enable_progress_bar=False,
                        enable_model_summary=False, enable_checkpointing=False, accelerator="cpu")
    with one_job_of_processes():  # the spawn launcher's port, released afterwards
        trainer.fit(_TinyRestorerModule(backbone.transformer), data)
    (metrics,) = tmp_path.rglob("metrics.csv")  # written by rank 0 only
    with open(metrics) as handle:
        rows = [row for row in csv.DictReader(handle) if row.get("deploy/psnr_k3")]
    assert [int(row["step"]) for row in rows] == [1, 2]
