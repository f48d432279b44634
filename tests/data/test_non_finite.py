"""Non-finite numbers stop a run: never written to the cache, redone when found in it (as is a shard whose bytes
changed), and a NaN latent stops training at the batch that holds it (one line, exit 2, the last good checkpoint
kept)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file
from scene_builders import tiny_configs
from support.inputs import overwrite_tensor_bytes

from tracegs.data.config import DataModuleConfig
from tracegs.data.datamodule import PairedClipDataModule
from tracegs.data.preparation.driver import run_prepare
from tracegs.data.preparation.shards import shard_is_valid
from tracegs.errors import NonFiniteError
from tracegs.io import read_safetensors, save_safetensors_atomic, seal_header


def poison(shard: Path, key: str = "latent/target") -> None:
    """Put one NaN into ``key`` of a shard, as a buggy encoder would (bypassing the writer's guard, with a
    checksum of the poisoned bytes, so only the non-finite checks can catch it)."""
    tensors, metadata = read_safetensors(shard, fix="")
    tensors[key] = tensors[key].clone()
    tensors[key].view(-1)[0] = float("nan")
    save_file(tensors, str(shard), metadata=metadata)
    seal_header(shard)


def test_a_non_finite_tensor_is_never_written(tmp_path):
    path = tmp_path / "shard.safetensors"
    with pytest.raises(NonFiniteError, match=r"shard.safetensors: non-finite values in tensors \['latent/b'\]"):
        save_safetensors_atomic({"latent/a": torch.zeros(2), "latent/b": torch.tensor([1.0, float("inf")])}, path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("damage", [poison, overwrite_tensor_bytes], ids=["nan", "overwritten_bytes"])
def test_prepare_redoes_a_damaged_shard(tmp_path, prepared, backbone, damage):
    tmp, _, _, _, _ = prepared
    for part in ("synthetic", "work", "cache"):
        shutil.copytree(tmp / part, tmp_path / part)
    synthetic, source, prepare = tiny_configs(tmp_path)
    shard = tmp_path / "cache" / "scene_000" / "clip_001.safetensors"
    intact = shard.read_bytes()
    damage(shard)
    assert not shard_is_valid(shard)
    run_prepare(prepare, source, backbone, synthetic, progress=False)
    assert shard.read_bytes() == intact


def first_step_with_clip(cache: Path, clip: int, batch_size: int, seed: int) -> int:
    """The optimiser step whose batch first holds ``clip``, in the order the real data module serves."""
    module = PairedClipDataModule(DataModuleConfig(cache_dir=str(cache), student_views=[3], student_snapshots=[8],
                                                   batch_size=batch_size, seed=seed))
    module.setup("fit")
    for step, batch in enumerate(module.train_dataloader()):
        if clip in batch["clip"].tolist():
            return step
    raise AssertionError(f"clip {clip} never served")


def test_nan_in_a_cached_latent_stops_training_at_its_batch(tmp_path, prepared, entry_point):
    tmp, _, _, _, _ = prepared
    cache = tmp_path / "cache"
    shutil.copytree(tmp / "cache", cache)
    poison(cache / "scene_000" / "clip_001.safetensors")
    step = first_step_with_clip(cache, clip=1, batch_size=1, seed=0)
    result = entry_point("train", [
        "stage=baseline", f"data.datamodule.cache_dir={cache}", "data.datamodule.student_views=[3]",
        "data.datamodule.student_snapshots=[8]", "data.datamodule.seed=0", "data.prepare.student_views=[3]",
        "data.prepare.student_snapshots=[8]", "data.prepare.fit.iterations=16",
        "data.prepare.fit.snapshot_iters=[8,16]", "stage.batch_size=1",
        "stage.max_steps=4", "stage.checkpoint_every_n_steps=1", "trainer.loggers=[]", f"paths.root_dir={tmp_path}",
    ], tmp_path)
    lines = result.stderr_lines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-3000:]
    assert f"step {step}: non-finite loss" in lines[0] and "scene_000/clip_001" in lines[0], lines[0]
    (run_dir,) = (tmp_path / "outputs" / "embedded" / "baseline").iterdir()  # the run's identity folder
    assert not (run_dir / "baseline_transformer").exists()
    if step == 0:
        assert not (run_dir / "checkpoints" / "last.ckpt").exists()
    else:  # the last good checkpoint is the one after the previous step, and it holds finite weights
        last = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True)
        assert last["global_step"] == step
        assert all(torch.isfinite(w).all() for w in last["state_dict"].values())
