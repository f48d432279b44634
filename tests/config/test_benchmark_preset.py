"""`make benchmark`: the preset composes, every step's command validates, the replicates share what does not
depend on the training seed and each finds its own upstream products."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose
from omegaconf import OmegaConf

from tracegs.config.validate import validate
from tracegs.pipeline.benchmark import benchmark_steps, estimate_minutes
from tracegs.pipeline.upstream import upstream_config

APP_CONFIG = {"prepare": "prepare", "train": "train", "evaluate": "evaluate", "report": "report"}


pytestmark = pytest.mark.usefixtures("hydra_context")  # tests/conftest.py


def test_preset_has_enough_scenes_and_seeds():
    cfg = compose(config_name="benchmark")
    validate(cfg)
    assert cfg.experiment.name == "benchmark"
    assert len(cfg.data.synthetic.test_seeds) >= 8
    assert len(cfg.benchmark.training_seeds) >= 3
    assert 3 in cfg.evaluation.views
    # Apart from the scenes and the deployment tables' settings, it is the demo's experiment unchanged.
    embedded = compose(config_name="demo")
    for key in ("experiment.baseline_steps", "experiment.stage1_steps", "experiment.stage2_steps", "backbone",
                "deploy.total_iters", "data.prepare.student_views", "data.synthetic.train_seeds"):
        assert OmegaConf.select(cfg, key) == OmegaConf.select(embedded, key), key


def test_the_default_run_fits_the_hour():
    cfg = compose(config_name="benchmark")
    steps = benchmark_steps(cfg.ablation.name, cfg.seed, list(cfg.benchmark.training_seeds), Path("/tmp/bench"))
    minutes = estimate_minutes(len(cfg.data.synthetic.train_seeds), len(cfg.data.synthetic.test_seeds),
                               len(cfg.evaluation.views), len(cfg.benchmark.training_seeds), len(steps),
                               cfg.benchmark.held_out_clips_per_scene)
    assert minutes < 52  # leaves a margin under 60 min for the estimate's error
    # At the demo's scale with every view count: the measured stages plus the privileged gap it does not run.
    demo = estimate_minutes(12, 2, 3, 1, 0, 8)
    test_prepare = 2 * 1.0 * (3 * 340 + 600) / (4 * 600)
    assert demo == pytest.approx(6.7 + test_prepare + 3.1 + 7.2 + 2 * 8 * 2 * 7 * 0.5 / 60, abs=0.01)


def test_every_step_composes_and_validates(tmp_path, as_hydra_job):
    # Run folders are named like this one: commas, brackets and '=' must reach the children as one value.
    out_dir = tmp_path / "seed0,iterations=40,test_seeds=_100,101_-cecb1709"
    for step in benchmark_steps("F", 0, [0, 1], out_dir, ["paths.root_dir=/tmp/elsewhere"]):
        cfg = as_hydra_job(APP_CONFIG[step.app], list(step.overrides))
        validate(cfg)
        assert cfg.paths.root_dir == "/tmp/elsewhere"
        if step.app == "evaluate":
            assert Path(cfg.evaluation.out_dir).parent == out_dir / "eval"
            assert cfg.evaluation.held_out_cache == str(out_dir / "cache" / "test")


def _step(steps, label):
    return next(s for s in steps if s.label == label)


def test_replicates_share_data_and_3dgs_but_not_the_restorer(tmp_path, as_hydra_job):
    steps = benchmark_steps("F", 0, [0, 1], tmp_path)
    evaluations = [as_hydra_job("evaluate", list(_step(steps, f"seed {s}: evaluate {m}").overrides))
                   for s, m in ((0, "[3dgs,baseline,tracegs]"), (1, "[baseline,tracegs]"))]
    first, second = evaluations
    # What plain 3DGS depends on is identical, so the first replicate's 3DGS serves every seed.
    for key in ("deploy", "data.prepare.fit", "data.source", "data.synthetic", "evaluation.views",
                "evaluation.held_out_cache"):
        assert OmegaConf.select(first, key) == OmegaConf.select(second, key), key
    assert list(second.evaluation.methods) == ["baseline", "tracegs"]
    # The restorer is trained from scratch per seed: other model seeds, other folders, one shared cache.
    assert first.stage.seed != second.stage.seed
    assert first.data.datamodule.seed != second.data.datamodule.seed
    assert first.data.datamodule.cache_dir == second.data.datamodule.cache_dir == str(tmp_path / "cache" / "train")
    assert first.evaluation.out_dir != second.evaluation.out_dir


def test_each_replicate_finds_its_own_upstream_products(tmp_path, as_hydra_job):
    steps = benchmark_steps("F", 0, [0, 1], tmp_path)
    for seed in (0, 1):
        trained = {stage: str(as_hydra_job("train", list(_step(steps, f"seed {seed}: train {label}").overrides))
                              .run_dir)
                   for stage, label in (("baseline", "A"), ("stage1", "Stage 1"), ("stage2", "Stage 2"))}
        methods = "[3dgs,baseline,tracegs]" if seed == 0 else "[baseline,tracegs]"
        evaluation = as_hydra_job("evaluate", list(_step(steps, f"seed {seed}: evaluate {methods}").overrides))
        for stage, folder in trained.items():
            assert str(upstream_config(evaluation, stage).run_dir) == folder, (seed, stage)
        stage2 = as_hydra_job("train", list(_step(steps, f"seed {seed}: train Stage 2").overrides))
        assert str(upstream_config(stage2, "stage1").run_dir) == trained["stage1"]
        gap = as_hydra_job("report", list(_step(steps, f"seed {seed}: privileged gap").overrides))
        for stage in ("stage1", "stage2"):
            assert str(upstream_config(gap, stage).run_dir) == trained[stage], (seed, stage)
    assert len({str(as_hydra_job("train", list(_step(steps, f"seed {s}: train A").overrides)).run_dir)
                for s in (0, 1)}) == 2


def test_seeds_must_be_listed_once(tmp_path):
    with pytest.raises(ValueError, match="repeats"):
        benchmark_steps("F", 0, [1, 1], tmp_path)
    with pytest.raises(ValueError, match="at least one"):
        benchmark_steps("F", 0, [], tmp_path)
