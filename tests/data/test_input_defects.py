"""Inputs a user hands in, through the real entry points: names that would leave the root, captures too small
for ``capture.views``, adapters of another kind and cache shards whose bytes changed. Each gives exit code 2,
one line on stderr naming the file or field, no file outside the root and nothing in a product folder."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from scene_builders import write_scene
from support.inputs import (
    TINY_PREPARE,
    TINY_RESTORE,
    assert_refused,
    files_under,
    overwrite_tensor_bytes,
    tiny_backbone_config,
)

from tracegs.data.datamodule import CacheError
from tracegs.eval.clips import held_out_clips
from tracegs.io import read_safetensors, save_safetensors_atomic
from tracegs.restorer import adapters
from tracegs.restorer.build import create_transformer


def student_adapter(path: Path, stage: str = "stage2", dtype: torch.dtype = torch.float32, seed: int = 0) -> Path:
    """An adapter file as ``stage`` writes it, on a tiny base made in memory from ``seed``."""
    torch.manual_seed(seed)
    model = create_transformer(tiny_backbone_config().transformer)
    adapters.add_adapter(model, "a", tiny_backbone_config().lora)
    adapters.save_adapter(model, "a", path, stage=stage)
    if dtype != torch.float32:  # converted afterwards, as another tool would (the records are kept as they were)
        tensors, metadata = read_safetensors(path, "")
        save_safetensors_atomic({k: v.to(dtype) for k, v in tensors.items()}, path, metadata=metadata)
    return path


# --- builders: each sets up its case under tmp/root and returns (app, overrides, text the line must name) ---
def evaluation_scene_outside_the_root(root: Path):
    return ("evaluate", ["evaluation.scenes=[../../outside/x]"],
            "config field 'evaluation.scenes': '../../outside/x' holds a path separator")


def source_scene_dot_dot(root: Path):
    return "prepare", [*TINY_PREPARE, "data.source.scenes=[..]"], "config field 'data.source.scenes': '..' is empty"


def experiment_name_outside_the_root(root: Path):
    return "train", ["stage=stage1", "experiment.name=../../../outside"], "config field 'experiment.name'"


def scene_list_line_outside_the_root(root: Path):
    write_scene(root / "scenes" / "ring", n=12)
    listing = root / "scenes" / "train.txt"
    listing.write_text("ring\n../../outside  # not a scene of this root\n")
    return ("prepare", [*TINY_PREPARE, f"data.source.root={root / 'scenes'}", f"data.source.train_list={listing}"],
            f"{listing}: line 2: '../../outside' holds a path separator")


def capture_views_zero(root: Path):
    scene, _ = write_scene(root / "scenes" / "ring", n=12)
    return ("restore", [*TINY_RESTORE, f"capture.path={scene}", "capture.views=0"],
            "config field 'capture.views': 0 is out of range: must be >= 2 (deployment's clips run between two "
            "captured reference views)")


def capture_views_above_the_capture(root: Path):
    scene, _ = write_scene(root / "scenes" / "ring", n=12)
    return ("restore", [*TINY_RESTORE, f"capture.path={scene}", "capture.views=11"],
            f"config field 'capture.views': 11: {scene}: asked for 11 training views, but of the scene's 12 images "
            "2 are held out for testing, leaving 10 usable")


def one_image_capture(root: Path):
    scene, _ = write_scene(root / "scenes" / "single", n=1)
    return ("restore", [*TINY_RESTORE, f"capture.path={scene}", "capture.views=3"],
            "config field 'capture.views': 3: ")


def stage1_adapter_as_student(root: Path):
    path = student_adapter(root / "stage1_adapter.safetensors", stage="stage1")
    return ("deploy", ["artifacts.baseline_weights=null", f"artifacts.student_adapter={path}"],
            f"{path}: adapter of another kind: stage 'stage1' in the file, 'stage2' here")


def half_precision_student(root: Path):
    path = student_adapter(root / "student_fp16.safetensors", dtype=torch.float16)
    return ("deploy", ["artifacts.baseline_weights=null", f"artifacts.student_adapter={path}"],
            "dtype 'float16' in the file, 'float32' here")


def bf16_stage1_adapter(root: Path):
    path = student_adapter(root / "stage1_bf16.safetensors", stage="stage1", dtype=torch.bfloat16)
    return ("train", ["stage=stage2", "stage.base_weights=null", f"stage.init_adapter={path}"],
            "dtype 'bfloat16' in the file, 'float32' here")


def student_adapter_as_stage1(root: Path):
    path = student_adapter(root / "student.safetensors")
    return ("train", ["stage=stage2", "stage.base_weights=null", f"stage.init_adapter={path}"],
            f"{path}: adapter of another kind: stage 'stage2' in the file, 'stage1' here")


def adapter_of_another_base(root: Path):
    path = student_adapter(root / "student.safetensors", seed=123)
    return ("deploy", ["artifacts.baseline_weights=null", f"artifacts.student_adapter={path}"],
            f"{path}: adapter of another kind: base 'in-memory ")


CASES: dict[str, Callable[[Path], tuple[str, list[str], str]]] = {
    f.__name__: f
    for f in (evaluation_scene_outside_the_root, source_scene_dot_dot, experiment_name_outside_the_root,
              scene_list_line_outside_the_root, capture_views_zero, capture_views_above_the_capture,
              one_image_capture, stage1_adapter_as_student, half_precision_student, bf16_stage1_adapter,
              student_adapter_as_stage1, adapter_of_another_base)
}


@pytest.mark.parametrize("case", list(CASES))
def test_defect_gives_one_line_exit_2_and_writes_nothing(tmp_path, entry_point, case):
    root = tmp_path / "a" / "b" / "root"  # deep enough that '../../..' stays inside tmp_path, where we look
    root.mkdir(parents=True)
    app, overrides, expected = CASES[case](root)
    before = files_under(tmp_path)
    result = entry_point(app, [*overrides, f"paths.root_dir={root}"], root)
    written = files_under(tmp_path) - before
    assert_refused(result, app, expected, written)
    assert all(root in p.parents for p in written), sorted(written)  # nothing outside the root


def test_a_shard_with_overwritten_bytes_is_refused_by_training_and_evaluation(tmp_path, prepared, entry_point):
    tmp, _, _, _, _ = prepared
    cache = tmp_path / "cache"
    shutil.copytree(tmp / "cache", cache)
    shard = cache / "scene_000" / "clip_001.safetensors"
    overwrite_tensor_bytes(shard)
    result = entry_point("train", [
        "stage=baseline", f"data.datamodule.cache_dir={cache}", "data.datamodule.student_views=[3]",
        "data.datamodule.student_snapshots=[8]", "data.prepare.student_views=[3]", "data.prepare.student_snapshots=[8]",
        "data.prepare.fit.iterations=16", "data.prepare.fit.snapshot_iters=[8,16]", "stage.batch_size=1",
        "stage.max_steps=2", "trainer.loggers=[]", f"paths.root_dir={tmp_path}",
    ], tmp_path)
    lines = result.stderr_lines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-3000:]
    assert f"{shard}: tensors ['latent/target'] differ from the checksums written with them" in lines[0], lines[0]
    assert not (tmp_path / "outputs").exists()  # no checkpoint, no product: the run folder removed again
    with pytest.raises(CacheError, match=f"{shard}: tensors \\['latent/target'\\] differ"):
        held_out_clips(cache)
