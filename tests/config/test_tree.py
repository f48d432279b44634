"""The config tree read explicitly (tracegs.config.tree): a command's lookups of other configs (a variant's
sections, a stage option) need no Hydra context, so ``train(cfg)`` runs from Python as it runs in a command."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from tracegs.config.schema import register_configs
from tracegs.config.tree import ConfigTree
from tracegs.location import CONF_DIR
from tracegs.pipeline.records import write_run_record
from tracegs.pipeline.runner import composed
from tracegs.pipeline.train import train
from tracegs.pipeline.upstream import locate_artifacts


@pytest.fixture
def hydra_closed():
    """Configs composed as a command composes them, then every Hydra context closed."""
    register_configs()

    def compose(config_name: str, overrides: list[str]):
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            return composed(config_name, overrides)

    return compose


def test_the_tree_a_command_composed_on_composes_as_hydra_does(hydra_closed):
    overrides = ["stage=stage1", "ablation=E"]
    cfg = hydra_closed("train", overrides)
    assert not GlobalHydra.instance().is_initialized()
    tree = ConfigTree.of(cfg)
    assert tree == ConfigTree.at(CONF_DIR)
    again = tree.compose("train", overrides)
    again.command_line, again.config_search_path = cfg.command_line, cfg.config_search_path  # what composed records
    assert OmegaConf.to_yaml(again) == OmegaConf.to_yaml(cfg)
    # A stage option as its file is written, interpolations and all.
    assert tree.option("stage", "stage1") == OmegaConf.to_container(
        OmegaConf.load(Path(CONF_DIR) / "stage" / "stage1.yaml"), resolve=False)


def test_train_runs_with_no_hydra_context_open(hydra_closed, tmp_path):
    """Stage 1 on a root with A and Stage 1 finished: ``train(cfg)`` locates A through the default variant's
    sections and A's stage option, and finds its own product finished (nothing trained)."""
    root = f"paths.root_dir={tmp_path}"
    baseline = hydra_closed("train", [root, "stage=baseline"])
    (Path(baseline.run_dir) / "baseline_transformer").mkdir(parents=True)
    (Path(baseline.run_dir) / "baseline_transformer" / "config.json").write_text("{}")
    write_run_record(baseline, "baseline", baseline.run_dir)
    finished = hydra_closed("train", [root, "stage=stage1"])
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        locate_artifacts(finished, ["baseline_weights"])
    (Path(finished.run_dir) / "stage1_adapter").mkdir(parents=True)
    write_run_record(finished, "stage1", finished.run_dir)

    cfg = hydra_closed("train", [root, "stage=stage1"])
    assert not GlobalHydra.instance().is_initialized()
    assert train(cfg) == Path(finished.run_dir) / "stage1_adapter"
    assert cfg.artifacts.baseline_weights == str(Path(baseline.run_dir) / "baseline_transformer")
