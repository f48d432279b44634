"""`make replicate`: the preset composes, every step's command validates, the replicates share what does not
depend on the training seed, and each variant and seed finds its own upstream products."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from hydra import compose
from omegaconf import OmegaConf

from tracegs.config.tree import ConfigTree
from tracegs.config.validate import validate
from tracegs.errors import ConfigError
from tracegs.location import CONF_DIR
from tracegs.pipeline.diagnostics import diagnostics_report
from tracegs.pipeline.replicate import (
    estimate_minutes,
    replicate_steps,
    replicate_variants,
    variant_teachers,
)
from tracegs.pipeline.runner import Step
from tracegs.pipeline.upstream import upstream_config
from tracegs.pipeline.variants import table3_variants

APP_CONFIG = {"prepare": "prepare", "train": "train", "evaluate": "evaluate", "report": "report"}

TREE = ConfigTree.at(CONF_DIR)  # the package's config tree


pytestmark = pytest.mark.usefixtures("hydra_context")  # tests/conftest.py


def test_preset_has_enough_scenes_and_seeds():
    cfg = compose(config_name="replicate")
    validate(cfg)
    assert cfg.experiment.name == "replicate"
    assert len(cfg.data.synthetic.test_seeds) >= 8
    assert len(cfg.replicate.training_seeds) >= 3
    assert 3 in cfg.evaluation.views
    # Apart from the scenes and the deployment tables' settings, it is the demo's experiment unchanged.
    embedded = compose(config_name="demo")
    for key in ("experiment.baseline_steps", "experiment.stage1_steps", "experiment.stage2_steps", "backbone",
                "deploy.total_iters", "data.prepare.student_views", "data.synthetic.train_seeds"):
        assert OmegaConf.select(cfg, key) == OmegaConf.select(embedded, key), key


def test_the_default_run_estimate_is_bounded_and_follows_the_config():
    cfg = compose(config_name="replicate")
    variants = replicate_variants(TREE)
    steps = replicate_steps(variants, cfg.seed, list(cfg.replicate.training_seeds), Path("/tmp/bench"))
    parts = estimate_minutes(cfg, variants, steps)
    # The multi-step default trains 200 Stage-2 steps per student and seed (estimate ~74 min): the bound keeps the
    # estimate from growing unnoticed; the measured run is in the README.
    assert sum(parts.values()) < 80
    # The estimate follows the config's sizes: each further training seed costs a seed's training,
    # deployment and diagnostics, and nothing more of the data; three view counts deploy three times as much.
    more_seeds = estimate_minutes(compose(config_name="replicate", overrides=["replicate.training_seeds=[0,1,2,3]"]),
                                  variants, steps)
    for part in ("training", "diagnostics"):
        assert more_seeds[part] == pytest.approx(parts[part] * 4 / 3)
    assert more_seeds["data"] == parts["data"]
    every_view = estimate_minutes(compose(config_name="replicate", overrides=["evaluation.views=[3,6,9]"]),
                                  variants, steps)
    assert every_view["deployment"] == pytest.approx(3 * parts["deployment"])


def test_every_variant_is_run_and_the_caches_hold_every_teacher():
    variants = replicate_variants(TREE)
    assert [v.name for v in variants] == [v.name for v in table3_variants(TREE)]  # conf/ablation/, Table 3's rows
    # C and D need the 12- and 18-view teachers, B the sparse fits' final snapshots (as the sweep prepares).
    assert variant_teachers(variants, [3, 6, 9]) == {"data.prepare.dense_views": [12, 18, None],
                                                     "data.prepare.student_final_fits": True}
    chosen = replicate_variants(TREE, ["F", "A"])
    assert [v.name for v in chosen] == ["A", "F"] and not chosen[0].trained
    assert variant_teachers(chosen, [3, 6, 9]) == {"data.prepare.dense_views": [None],
                                                   "data.prepare.student_final_fits": False}
    for names, problem in ((["A", "G"], r"\['G'\] are not variants"), (["A", "A"], "repeats"), ([], "at least one")):
        with pytest.raises(ConfigError, match=f"replicate.variants.*{problem}"):
            replicate_variants(TREE, names)


def _single(steps) -> list[Step]:
    """The steps as single runs: a multirun's jobs, one per variant (how Hydra expands ``ablation=A,F``), without
    its multirun folder."""
    return [replace(job, settings=tuple((k, v) for k, v in job.settings if k != "hydra.sweep.dir"))
            for step in steps for job in step.jobs()]


def test_every_step_composes_and_validates(tmp_path, entry_config):
    # Run folders are named like this one: commas, brackets and '=' must reach the children as one value.
    out_dir = tmp_path / "seed0,iterations=40,test_seeds=_100,101_-cecb1709"
    steps = replicate_steps(replicate_variants(TREE, ["A", "F"]), 0, [0], out_dir, ["paths.root_dir=/tmp/elsewhere"])
    for step in _single(steps):
        cfg = entry_config(APP_CONFIG[step.app], list(step.overrides))
        validate(cfg)
        assert cfg.paths.root_dir == "/tmp/elsewhere"
        if step.app == "evaluate" and "3DGS" not in step.label:
            seed, variant = cfg.seed, cfg.ablation.name
            assert Path(cfg.evaluation.out_dir) == out_dir / "eval" / f"seed{seed}" / variant
            assert list(cfg.evaluation.methods) == [str(cfg.ablation.method)]
        if step.app == "report":
            assert cfg.evaluation.held_out_cache == str(out_dir / "cache" / "test")


def _step(steps, label):
    return next(s for s in steps if s.label == label)


def _taking_a(steps: list[Step], a_run: str) -> list[Step]:
    """The steps with what they take of A's run filled in, as the runner fills it after A's step."""
    return [step.with_settings({key: f"{a_run}/{spec.partition('/')[2]}" for key, spec in step.takes.items()})
            for step in steps]


def test_replicates_share_data_3dgs_and_a_but_not_the_distilled_restorers(tmp_path, entry_config):
    steps = _single(replicate_steps(replicate_variants(TREE, ["A", "F"]), 0, [0, 1], tmp_path))
    plain = entry_config("evaluate", list(_step(steps, "evaluate plain 3DGS").overrides))
    a_run = str(entry_config("train", list(_step(steps, "train A").overrides)).run_dir)
    steps = _taking_a(steps, a_run)
    evaluations = [entry_config("evaluate", list(_step(steps, f"seed {s}: evaluate (A,F) F").overrides))
                   for s in (0, 1)]
    # What plain 3DGS depends on is identical to every variant's deployment, so it is evaluated once.
    for cfg in evaluations:
        for key in ("deploy", "data.prepare.fit", "data.source", "data.synthetic", "evaluation.views"):
            assert OmegaConf.select(plain, key) == OmegaConf.select(cfg, key), key
        # A is made once and frozen, as the paper's A is one released model.
        assert cfg.artifacts.baseline_weights == f"{a_run}/baseline_transformer"
    assert list(plain.evaluation.methods) == ["3dgs"]
    first, second = evaluations
    # Stage 1 and the students are trained from scratch per seed: other model seeds, other folders, one cache.
    assert first.stage.seed != second.stage.seed
    assert first.data.datamodule.seed != second.data.datamodule.seed
    assert first.data.datamodule.cache_dir == second.data.datamodule.cache_dir == str(tmp_path / "cache" / "train")
    assert first.evaluation.out_dir != second.evaluation.out_dir
    assert not [s for s in steps if s.label.startswith("seed") and s.label.endswith("train A")]


def test_each_replicate_finds_its_own_upstream_products(tmp_path, entry_config):
    steps = _single(replicate_steps(replicate_variants(TREE, ["A", "F"]), 0, [0, 1], tmp_path))
    labels = [step.label for step in steps]
    # The paper's data protocol: A on its own scenes, then the training clips whose pseudo-targets A makes.
    assert labels[:3] == ["prepare (A's pretraining scenes)", "train A", "prepare (training scenes)"]
    a_run = str(entry_config("train", list(_step(steps, "train A").overrides)).run_dir)
    training_data = entry_config("prepare", list(_step(steps, "prepare (training scenes)").overrides))
    assert str(upstream_config(training_data, "baseline").run_dir) == a_run
    steps = _taking_a(steps, a_run)
    for seed in (0, 1):
        stage1 = entry_config("train", list(_step(steps, f"seed {seed}: train Stage 1").overrides))
        assert stage1.stage.base_weights == f"{a_run}/baseline_transformer"
        stage2 = entry_config("train", list(_step(steps, f"seed {seed}: train Stage 2 (F) F").overrides))
        assert str(upstream_config(stage2, "stage1").run_dir) == str(stage1.run_dir)
        evaluation = entry_config("evaluate", list(_step(steps, f"seed {seed}: evaluate (A,F) F").overrides))
        assert str(upstream_config(evaluation, "stage2").run_dir) == str(stage2.run_dir), seed
        for kind in ("privileged gap", "trajectory diagnostics"):
            report = entry_config("report", list(_step(steps, f"seed {seed}: {kind}").overrides))
            assert str(upstream_config(report, "stage1").run_dir) == str(stage1.run_dir), (seed, kind)
            assert report.artifacts.baseline_weights == f"{a_run}/baseline_transformer"
        assert list(report.report.inputs) == ["A", "F"] and report.ablation.name == "F"


def test_seeds_must_be_listed_once(tmp_path):
    variants = replicate_variants(TREE, ["A", "F"])
    with pytest.raises(ValueError, match="repeats"):
        replicate_steps(variants, 0, [1, 1], tmp_path)
    with pytest.raises(ValueError, match="at least one"):
        replicate_steps(variants, 0, [], tmp_path)


def test_diagnostics_need_a_held_out_cache_and_known_variants(tmp_path, entry_config):
    cfg = entry_config("report", ["report.kind=diagnostics", f"paths.root_dir={tmp_path}"])
    with pytest.raises(ConfigError, match="evaluation.held_out_cache.*prepared held-out cache"):
        diagnostics_report(cfg)
    cfg = entry_config("report", ["report.kind=diagnostics", "report.inputs=[A,G]", f"paths.root_dir={tmp_path}",
                                  f"evaluation.held_out_cache={tmp_path}"])
    with pytest.raises(ConfigError, match=r"report.inputs.*\['G'\] are not variants"):
        diagnostics_report(cfg)
    cfg = entry_config("report", ["report.kind=diagnostics", "report.inputs=[A]", "report.stage1_row=true",
                                  f"paths.root_dir={tmp_path}", f"evaluation.held_out_cache={tmp_path}"])
    with pytest.raises(ConfigError, match="report.stage1_row.*needs a distilled variant"):
        diagnostics_report(cfg)
    assert not any(tmp_path.iterdir())  # refused before any work
