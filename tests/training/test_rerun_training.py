"""A finished training run exports what its first completion exported: the last step is always checkpointed, a
checkpoint already at ``max_steps`` exports what it holds (the EMA average where the stage averages), no ``-v1``
files; a checkpoint whose hyper_parameters name code to import is refused before Lightning sees it."""

from __future__ import annotations

import shutil
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from support.training_runs import config, product_bytes, write_cache

from tracegs.errors import InputFileError
from tracegs.training.checkpoints import require_loadable_checkpoint
from tracegs.training.run import train_stage

STEPS = 5  # not a multiple of the checkpoint interval below


@pytest.fixture(scope="module")
def averaged_baseline(tmp_path_factory):
    """(config, product bytes) of a baseline run that averages its weights and checkpoints every 2 steps."""
    tmp = tmp_path_factory.mktemp("rerun")
    cfg = config(tmp, write_cache(tmp / "cache"), "baseline", STEPS, "baseline", ema_decay=0.5)
    cfg = replace(cfg, stage=replace(cfg.stage, checkpoint_every_n_steps=2))
    return cfg, product_bytes(train_stage(cfg))


def test_the_last_step_is_checkpointed(averaged_baseline):
    cfg, _ = averaged_baseline
    last = Path(cfg.output_dir) / "checkpoints" / "last.ckpt"
    assert torch.load(last, map_location="cpu", weights_only=True)["global_step"] == STEPS


def test_a_finished_run_exports_its_average_again_and_writes_no_second_checkpoint(averaged_baseline):
    """Killed after the last checkpoint and before the export (the product is gone): the rerun trains nothing
    and exports the average the first completion exported, not the raw last-step weights."""
    cfg, first = averaged_baseline
    out = Path(cfg.output_dir)
    last = out / "checkpoints" / "last.ckpt"
    saved = last.stat().st_mtime_ns
    checkpoint = torch.load(last, map_location="cpu", weights_only=True)
    assert any(not torch.equal(checkpoint["state_dict"][k], checkpoint["current_model_state"][k])
               for k in checkpoint["state_dict"])  # the average differs from the raw weights
    for again in range(2):
        product = train_stage(cfg)
        assert product_bytes(product) == first, f"rerun {again}"
        shutil.rmtree(product)
    assert last.stat().st_mtime_ns == saved  # nothing trained, nothing saved
    assert sorted(p.name for p in (out / "checkpoints").iterdir() if "-v" in p.name) == []


@pytest.mark.parametrize("key", ["_instantiator", "_class_path"])
def test_a_checkpoint_naming_code_to_import_is_refused(averaged_baseline, tmp_path, key):
    cfg, _ = averaged_baseline
    checkpoint = torch.load(Path(cfg.output_dir) / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    checkpoint["hyper_parameters"] = {**checkpoint.get("hyper_parameters", {}), key: "planted_module.run"}
    planted = tmp_path / "planted.ckpt"
    torch.save(checkpoint, planted)
    with pytest.raises(InputFileError, match=rf"{key}.*arbitrary code") as error:
        require_loadable_checkpoint(planted, "stage.resume_from")
    assert str(planted) in str(error.value) and "\n" not in str(error.value)
    resumed = replace(cfg, stage=replace(cfg.stage, resume_from=str(planted)), output_dir=str(tmp_path / "other"))
    with pytest.raises(InputFileError, match=key):
        train_stage(resumed)
    assert "planted_module" not in sys.modules
    assert not (tmp_path / "other" / "baseline_transformer").exists()
