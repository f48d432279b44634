"""The paper's data protocol at the embedded default (supplement, "Pseudo-target generation"): variant A is trained
on scenes of its own and frozen, the training scenes' cache holds A's restorations of R_d as targets and is named
by A's settings, and the pretraining scenes never overlap the others."""

from __future__ import annotations

import pytest
from hydra import compose

from tracegs.config.validate import ConfigError, validate
from tracegs.pipeline.demo import demo_steps
from tracegs.pipeline.steps import sweep_steps

pytestmark = pytest.mark.usefixtures("hydra_context")  # tests/conftest.py


def cache(split: str, *overrides: str) -> str:
    return str(compose(config_name="prepare", overrides=[f"data.prepare.split={split}", *overrides])
               .data.prepare.cache_dir)


def test_a_is_trained_on_its_own_scenes_and_the_stages_on_the_training_scenes():
    baseline = compose(config_name="train", overrides=["stage=baseline"])
    assert baseline.experiment.baseline_split == "pretrain"
    assert str(baseline.data.datamodule.cache_dir) == cache("pretrain")
    for stage in ("stage1", "stage2"):
        assert str(compose(config_name="train", overrides=[f"stage={stage}"]).data.datamodule.cache_dir) == \
            cache("train")
    gt = compose(config_name="train", overrides=["stage=baseline", "experiment=embedded_gt_targets"])
    assert str(gt.data.datamodule.cache_dir) == cache("train", "experiment=embedded_gt_targets")


@pytest.mark.parametrize("a_setting", ["experiment.baseline_lr=3e-4", "experiment.baseline_steps=7",
                                       "data.synthetic.pretrain_seeds=[300]", "data.prepare.pretrain_pairs=captured"])
def test_the_training_cache_is_named_by_the_a_that_makes_its_pseudo_targets(a_setting):
    """A changed A is a new training cache (never stale pseudo-targets); the pretraining and held-out caches, which
    hold ground truth, keep their names unless their own scenes change."""
    assert cache("train", a_setting) != cache("train")
    assert cache("test", a_setting) == cache("test") and cache("val", a_setting) == cache("val")
    own_scenes = a_setting.startswith(("data.synthetic.pretrain_seeds", "data.prepare.pretrain_pairs"))
    assert (cache("pretrain", a_setting) != cache("pretrain")) == own_scenes
    # Under the ground-truth protocol the training cache does not read A.
    gt = ["experiment=embedded_gt_targets"]
    if not own_scenes:
        assert cache("train", *gt, a_setting) == cache("train", *gt)


def test_the_stages_and_the_prepare_command_name_the_same_training_cache():
    """Each command computes the cache's name from its own config: a stage's own sections must not enter it."""
    for stage in ("stage1", "stage2"):
        assert str(compose(config_name="train", overrides=[f"stage={stage}", "experiment.stage1_lr=3e-4"])
                   .data.datamodule.cache_dir) == cache("train", "experiment.stage1_lr=3e-4")


def test_pretraining_scenes_overlapping_another_split_are_refused_in_one_line():
    validate(compose(config_name="prepare", overrides=["data.prepare.split=pretrain"]))
    cfg = compose(config_name="prepare", overrides=["data.synthetic.pretrain_seeds=[200,50]"])
    with pytest.raises(ConfigError, match=r"pretrain_seeds must be disjoint.*\[50\]") as error:
        validate(cfg)
    assert "\n" not in str(error.value)


def test_a_comes_before_the_training_data_whose_targets_it_makes():
    labels = [step.label for step in demo_steps("F", [3], "out")]
    assert labels.index("prepare (A's pretraining scenes)") < labels.index("train A") < \
        labels.index("prepare (training scenes)") < labels.index("train Stage 1")
    gt = [step.label for step in demo_steps("F", [3], "out", pretrain=False)]
    assert "prepare (A's pretraining scenes)" not in gt
    assert gt.index("prepare (training scenes)") < gt.index("train A")
    sweep = [step.label for step in sweep_steps(["A", "F"], ["F"], pretrain=True)]
    assert sweep.index("train A") < sweep.index("prepare (training scenes, every teacher)")
