"""Every bad input through the real entry points: exit code 2, one line on stderr naming the file or field,
and nothing written but the error line in the run's log file (no Hydra record of a command that did nothing)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from scene_builders import write_scene
from support.inputs import assert_refused, files_under, tiny_backbone_config

from tracegs.restorer import adapters
from tracegs.restorer.build import create_transformer
from tracegs.restorer.config import LoraConfig


def adapter_file(path: Path, rank: int | None = None) -> Path:
    backbone = tiny_backbone_config()
    model = create_transformer(backbone.transformer)
    lora = backbone.lora if rank is None else LoraConfig(rank=rank, alpha=rank)
    adapters.add_adapter(model, "a", lora)
    adapters.save_adapter(model, "a", path)
    return path


def transformer_dir(path: Path) -> Path:
    create_transformer(tiny_backbone_config().transformer).save_pretrained(path)
    return path


def truncate(path: Path, keep: float = 0.5) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    return path


def scene_root(tmp: Path) -> Path:
    write_scene(tmp / "scenes" / "ring", n=12)
    return tmp / "scenes"


PREPARE = ["data=custom", "data.source.height=32", "data.source.width=48",
           "data.prepare.pseudo_target=dense", "data.prepare.student_snapshots=[140,340]",
           "data.prepare.frames_per_clip=9", "data.datamodule.student_snapshots=[140,340]"]


# --- builders: each damages its inputs under tmp and returns (app, overrides, text the line must name) ---
def truncated_png(tmp: Path):
    scenes = scene_root(tmp)
    image = truncate(scenes / "ring" / "images" / "img_003.png")
    return "prepare", [*PREPARE, f"data.source.root={scenes}"], f"{image}: cannot decode the image"


def empty_png(tmp: Path):
    scenes = scene_root(tmp)
    image = scenes / "ring" / "images" / "img_005.png"
    image.write_bytes(b"")
    return "prepare", [*PREPARE, f"data.source.root={scenes}"], f"{image}: cannot decode the image"


def scene_without_sparse(tmp: Path):
    scenes = scene_root(tmp)
    (scenes / "garden" / "images").mkdir(parents=True)
    return "prepare", [*PREPARE, f"data.source.root={scenes}"], f"{scenes / 'garden' / 'sparse/0'}: scene folder"


def truncated_stage1_adapter(tmp: Path):
    path = truncate(adapter_file(tmp / "stage1_adapter.safetensors"))
    return ("train", ["stage=stage2", "stage.base_weights=null", f"stage.init_adapter={path}"],
            f"{path}: not a readable safetensors file")


def stage1_adapter_of_another_rank(tmp: Path):
    path = adapter_file(tmp / "rank4.safetensors", rank=4)
    return ("train", ["stage=stage2", "stage.base_weights=null", f"stage.init_adapter={path}",
                      "backbone.lora.rank=8", "backbone.lora.alpha=8"],
            "rank 4 in the file, 8 in backbone.lora")


def garbage_student_adapter(tmp: Path):
    path = tmp / "student_adapter.safetensors"
    path.write_bytes(b"this is not a safetensors file" * 4)
    return ("deploy", ["artifacts.baseline_weights=null", f"artifacts.student_adapter={path}"],
            f"{path}: not a readable safetensors file")


def truncated_baseline_transformer(tmp: Path):
    directory = transformer_dir(tmp / "baseline_transformer")
    truncate(directory / "diffusion_pytorch_model.safetensors")
    return ("deploy", ["ablation=A", f"artifacts.baseline_weights={directory}"],
            f"{directory / 'diffusion_pytorch_model.safetensors'}: cannot load the transformer weights")


def baseline_directory_without_weights(tmp: Path):
    directory = transformer_dir(tmp / "baseline_transformer")
    (directory / "diffusion_pytorch_model.safetensors").unlink()
    return ("deploy", ["ablation=A", f"artifacts.baseline_weights={directory}"],
            f"{directory}: holds no diffusion_pytorch_model.safetensors, *.safetensors shards or "
            "diffusion_pytorch_model.bin")


def corrupt_checkpoint(tmp: Path):
    path = tmp / "last.ckpt"
    path.write_bytes(b"PK\x03\x04 truncated zip")
    return ("train", ["stage=stage1", "stage.base_weights=null", f"stage.resume_from={path}"],
            f"{path}: not a loadable training checkpoint")


def pickled_checkpoint(tmp: Path):
    path = tmp / "pickled.ckpt"
    torch.save({"state_dict": {}, "hyper_parameters": argparse.Namespace(lr=1.0)}, path)
    return ("train", ["stage=stage1", "stage.base_weights=null", f"stage.resume_from={path}"],
            f"{path}: holds Python objects that safe loading (weights_only) refuses")


def output_folder_is_a_file(tmp: Path):
    runs = tmp / "outputs"
    runs.write_text("not a folder")
    return "train", ["stage=stage1", f"paths.runs_dir={runs}"], f"{runs}: is a file"


def cache_folder_is_a_file(tmp: Path):
    scenes = scene_root(tmp)
    cache = tmp / "cache"
    cache.write_text("not a folder")
    return ("prepare", [*PREPARE, f"data.source.root={scenes}", f"data.prepare.cache_dir={cache}"],
            f"{cache}: is a file, but data.prepare.cache_dir needs a directory")


def misspelt_key_added_with_plus(tmp: Path):
    return "train", ["+stage.rollout_stpes=5"], "'stage.rollout_stpes': is not a field of the schema"


def misspelt_key(tmp: Path):
    return "train", ["stage.max_stepz=3"], "'stage.max_stepz': is not a field of the schema (misspelt?)"


def value_of_the_wrong_type(tmp: Path):
    return "train", ["stage.max_steps=abc"], "'stage.max_steps': Value 'abc' of type 'str' could not be converted"


def group_option_that_does_not_exist(tmp: Path):
    return "train", ["stage=stage3"], "config group 'stage' has no option 'stage3' (one of: baseline, stage1, stage2)"


CASES: dict[str, Callable[[Path], tuple[str, list[str], str]]] = {
    f.__name__: f
    for f in (truncated_png, empty_png, scene_without_sparse, truncated_stage1_adapter,
              stage1_adapter_of_another_rank, garbage_student_adapter, truncated_baseline_transformer,
              baseline_directory_without_weights, corrupt_checkpoint, pickled_checkpoint, output_folder_is_a_file,
              cache_folder_is_a_file, misspelt_key_added_with_plus, misspelt_key,
              value_of_the_wrong_type, group_option_that_does_not_exist)
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_gives_one_line_exit_2_and_writes_nothing(tmp_path, entry_point, case):
    app, overrides, expected = CASES[case](tmp_path)
    before = files_under(tmp_path)
    result = entry_point(app, [*overrides, f"paths.root_dir={tmp_path}"], tmp_path)
    assert_refused(result, app, expected, files_under(tmp_path) - before)
    assert not (tmp_path / "outputs").exists() or case == "output_folder_is_a_file"


def test_read_only_output_folder_is_named(tmp_path, entry_point, read_only):
    runs = tmp_path / "outputs"
    runs.mkdir()
    with read_only(runs):
        result = entry_point("train", ["stage=stage1", f"paths.runs_dir={runs}", f"paths.root_dir={tmp_path}"],
                             tmp_path)
    assert result.returncode == 2 and len(result.stderr_lines()) == 1, result.stderr[-3000:]
    assert f"{runs}: not writable" in result.stderr_lines()[0]
    assert list(runs.iterdir()) == []


def test_a_run_folder_that_held_something_keeps_it_and_gets_the_error_line(tmp_path, entry_point):
    """A refused command removes only a run folder it made itself; in one that held something before (an
    explicit ``run_dir`` of the user's), the error line reaches the run's log beside it, and Hydra's records of the
    command (``.hydra/``) are not written."""
    app, overrides, expected = corrupt_checkpoint(tmp_path)
    run_dir = tmp_path / "my_run"
    run_dir.mkdir()
    (run_dir / "notes.txt").write_text("the user's own file")
    result = entry_point(app, [*overrides, f"paths.root_dir={tmp_path}", f"run_dir={run_dir}"], tmp_path)
    assert result.returncode == 2
    assert (run_dir / "notes.txt").read_text() == "the user's own file"
    logs = list(run_dir.rglob("*.log"))
    assert logs and any(expected in log.read_text() for log in logs)
    assert not (run_dir / ".hydra").exists()
