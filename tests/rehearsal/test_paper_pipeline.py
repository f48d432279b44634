"""The paper pipeline under `experiment=rehearsal`: prepare -> Stage 1 -> Stage 2 -> deploy -> evaluate -> report.

Every component is the paper's class read from the paper's folder layouts (tests/rehearsal/paper_weights.py,
paper_scenes.py) through the entry points' own task functions. At paper scale variant A is GSFixer's
pretrained restorer: it is loaded (prepare's pseudo-targets, evaluation's baseline), never trained.

``test_paper_pipeline_rehearsal`` runs the rehearsal with ``SMOKE`` on top, the ``slow`` budgets test runs
it exactly, and the ``gpu`` test runs it on CUDA with gsplat.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from conftest import rehearsal_config, run_rehearsal_task
from safetensors import safe_open

from tracegs import tasks

# Test-time overrides of the default suite, each a budget knob (no science setting is touched).
SMOKE = (
    "experiment.stage1_steps=1",  # Stage 1 budget: one optimiser step
    "experiment.stage2_steps=2",  # Stage 2 budget: two optimiser steps, each a full N = 10 rollout
    "deploy.steps=2",  # reverse steps per deployed restoration (rehearsal: the full M = 50)
    "deploy.max_clips_per_round=1",  # restored clips per repair round (rehearsal: every reference pair)
    "evaluation.views=[3]",  # evaluated view counts (rehearsal: 3, 6, 9)
)
GPU = ("trainer.accelerator=gpu", "data.prepare.fit.backend=gsplat")  # the paper's devices and rasterizer


def run_pipeline(root: Path, extra: tuple[str, ...]) -> dict:
    """Every entry point in order under ``experiment=rehearsal`` (+ ``extra``); returns results.json."""
    run_rehearsal_task(tasks.prepare, root, "prepare", extra)
    assert run_rehearsal_task(tasks.train, root, "train", ("stage=baseline", *extra)) is None
    run_rehearsal_task(tasks.train, root, "train", ("stage=stage1", *extra))
    run_rehearsal_task(tasks.train, root, "train", ("stage=stage2", "ablation=F", *extra))
    run_rehearsal_task(tasks.deploy, root, "deploy", ("ablation=F", *extra))
    run_rehearsal_task(tasks.evaluate, root, "evaluate", ("ablation=F", *extra))
    results = run_rehearsal_task(tasks.report, root, "report", ("ablation=F", "report.kind=main", *extra))
    return json.loads(Path(results).read_text())


def check_products(root: Path, results: dict, views: list[int], extra: tuple[str, ...]) -> None:
    cfg = rehearsal_config(root, "evaluate", ("ablation=F", *extra))
    manifest = json.loads((Path(cfg.data.prepare.cache_dir) / "manifest.json").read_text())
    assert list(manifest["scenes"]) == ["scene_000"]  # the training list only, never the benchmark scene
    assert manifest["pseudo_target"] == "restorer" and manifest["frames_per_clip"] == 9
    clips = manifest["scenes"]["scene_000"]["clips"]
    assert len(clips) == cfg.data.prepare.clips_per_scene
    with safe_open(str(Path(cfg.data.prepare.cache_dir) / clips[0]), framework="pt") as shard:
        latent = shard.get_tensor("latent/target")
        assert latent.shape == (3, 16, 4, 6)  # 9 frames -> 3 latent frames, 32 x 48 -> 4 x 6 (VAE factor 8)
        assert shard.get_tensor("text").shape == (16, 32) and shard.get_tensor("ref_3d").shape[-1] == 64
    experiment = Path(cfg.paths.experiment_dir)
    assert not (experiment / "baseline").exists()  # variant A is loaded, not trained
    # Each stage's product in the folder its run identity names (tracegs.config.identity).
    stage1 = Path(rehearsal_config(root, "train", ("stage=stage1", *extra)).run_dir)
    stage2 = Path(rehearsal_config(root, "train", ("stage=stage2", "ablation=F", *extra)).run_dir)
    assert (stage1 / "stage1_adapter" / "adapter_config.json").is_file()
    assert (stage2 / "student_adapter" / "adapter_model.safetensors").is_file()
    deployed = Path(rehearsal_config(root, "deploy", ("ablation=F", *extra)).run_dir)
    assert (deployed / "scene_100").is_dir()
    assert results["meta"]["scenes"] == ["scene_100"]
    for method in ("3dgs", "baseline", "tracegs"):
        for k in views:
            assert math.isfinite(results[method][str(k)]["psnr"])


def fresh_root(tmp_path: Path, rehearsal_root: Path, paper_data: dict[str, Path]) -> Path:
    """A launch directory sharing the weights and the DL3DV scenes, with its own caches and outputs."""
    root = tmp_path / "launch"
    (root / "data").mkdir(parents=True)
    (root / "weights").symlink_to(rehearsal_root / "weights")
    (root / "data" / paper_data["dl3dv"].name).symlink_to(paper_data["dl3dv"])
    return root


# Slow until it fits the default suite's budget: 12.6 min on a loaded 2-core machine.
@pytest.mark.slow
def test_paper_pipeline_rehearsal(rehearsal_root, paper_data, vggt_double):
    results = run_pipeline(rehearsal_root, SMOKE)
    check_products(rehearsal_root, results, views=[3], extra=SMOKE)


@pytest.mark.slow
def test_paper_pipeline_rehearsal_at_rehearsal_budgets(tmp_path, paper_data, rehearsal_root, vggt_double):
    """The rehearsal exactly as configured (Stage 2's 20 steps, M = 50 at deployment, K = 3, 6, 9)."""
    root = fresh_root(tmp_path, rehearsal_root, paper_data)
    results = run_pipeline(root, ())
    check_products(root, results, views=[3, 6, 9], extra=())


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (and gsplat)")
def test_paper_pipeline_rehearsal_on_cuda_with_gsplat(tmp_path, paper_data, rehearsal_root, vggt_double):
    root = fresh_root(tmp_path, rehearsal_root, paper_data)
    results = run_pipeline(root, (*SMOKE, *GPU))
    check_products(root, results, views=[3], extra=(*SMOKE, *GPU))
