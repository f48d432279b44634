"""The paper pipeline under `experiment=rehearsal`: prepare -> Stage 1 -> Stage 2 -> deploy -> evaluate -> report.

Every component is the paper's class read from the paper's folder layouts (tests/rehearsal/paper_weights.py,
paper_scenes.py) through the entry points' own task functions, run as their console scripts run them
(tracegs.cli.app.run_task). At paper scale variant A is GSFixer's pretrained restorer: it is loaded (prepare's
pseudo-targets, evaluation's baseline), never trained.

``test_paper_pipeline_rehearsal`` (default suite) runs the rehearsal with ``BUDGET`` on top: smaller counts
only, each a size key of tests/support/rehearsal.py (SIZE_KEYS) or a count of units; the ``slow`` budgets test runs
it exactly, the ``slow`` DDP / FSDP tests train (and sweep) on two gloo CPU processes, and the ``gpu`` test runs
it on CUDA with gsplat.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import initialize_config_dir
from paper_weights import write_vggt_double_package
from safetensors import safe_open
from support.rehearsal import (
    BUDGET,
    SIZE_KEYS,
    fresh_root,
    rehearsal_config,
    rehearsal_job,
    rehearsal_run_dir,
    run_rehearsal_task,
)

from tracegs.cli.app import CONF_DIR
from tracegs.data.datamodule import clip_record, read_conditioning
from tracegs.pipeline.evaluate import deploy, evaluate
from tracegs.pipeline.prepare import prepare
from tracegs.pipeline.report import report
from tracegs.pipeline.runner import Step
from tracegs.pipeline.steps import out_of_domain_steps, restorer_steps
from tracegs.pipeline.train import train
from tracegs.pipeline.upstream import locate_artifacts
from tracegs.pipeline.variants import table3_variants

# Counts that experiment=rehearsal keeps at the paper's value but a test may lower: units of work.
UNIT_COUNTS = ("deploy.max_clips_per_round", "evaluation.views")
GPU = ("trainer.accelerator=gpu", "data.prepare.fit.backend=gsplat")  # the paper's devices and rasterizer


def run_pipeline(root: Path, extra: tuple[str, ...]) -> dict:
    """Every entry point in order under ``experiment=rehearsal`` (+ ``extra``); returns results.json."""
    run_rehearsal_task(prepare, root, "prepare", extra)
    assert run_rehearsal_task(train, root, "train", ("stage=baseline", *extra)) is None
    run_rehearsal_task(train, root, "train", ("stage=stage1", *extra))
    run_rehearsal_task(train, root, "train", ("stage=stage2", "ablation=F", *extra))
    run_rehearsal_task(deploy, root, "deploy", ("ablation=F", *extra))
    run_rehearsal_task(evaluate, root, "evaluate", ("ablation=F", *extra))
    results = run_rehearsal_task(report, root, "report", ("ablation=F", "report.kind=main", *extra))
    return json.loads(Path(results).read_text())


def check_products(root: Path, results: dict, views: list[int], extra: tuple[str, ...]) -> None:
    cfg = rehearsal_config(root, "evaluate", ("ablation=F", *extra))
    cache = rehearsal_run_dir(root, "prepare", extra, key="data.prepare.cache_dir")
    manifest = json.loads((cache / "manifest.json").read_text())
    assert list(manifest["scenes"]) == ["scene_000"]  # the training list only, never the benchmark scene
    assert manifest["pseudo_target"] == "restorer" and manifest["frames_per_clip"] == 9
    clips = manifest["scenes"]["scene_000"]["clips"]
    assert len(clips) == cfg.data.prepare.clips_per_scene
    with safe_open(str(cache / clips[0]), framework="pt") as shard:
        latent = shard.get_tensor("latent/target")
        assert latent.shape == (3, 16, 4, 6)  # 9 frames -> 3 latent frames, 32 x 48 -> 4 x 6 (VAE factor 8)
        assert not [k for k in shard.keys() if k.startswith("frames/")]  # a training cache holds latents only
    conditioning = read_conditioning(clip_record("scene_000", 0, cache / clips[0]))
    assert conditioning["text"].shape == (16, 32) and conditioning["ref_3d"].shape[-1] == 64
    experiment = Path(cfg.paths.experiment_dir)
    assert not (experiment / "baseline").exists()  # variant A is loaded, not trained
    # Each stage's product in the folder its run identity names (tracegs.config.identity).
    stage1 = rehearsal_run_dir(root, "train", ("stage=stage1", *extra))
    stage2 = rehearsal_run_dir(root, "train", ("stage=stage2", "ablation=F", *extra))
    assert (stage1 / "stage1_adapter" / "adapter_config.json").is_file()
    assert (stage2 / "student_adapter" / "adapter_model.safetensors").is_file()
    deployed = rehearsal_run_dir(root, "deploy", ("ablation=F", *extra))
    assert (deployed / "scene_100").is_dir()
    assert results["meta"]["scenes"] == ["scene_100"]
    for method in ("3dgs", "baseline", "tracegs"):
        for k in views:
            assert math.isfinite(results[method][str(k)]["psnr"])
            assert results[method][str(k)]["lpips"] > 0  # required at paper scale, from weights/vgg16-397923af.pth
    assert results["meta"]["lpips"].startswith("LPIPS-VGG")


def test_budget_overrides_are_sizes():
    keys = [override.split("=", 1)[0] for override in BUDGET]
    assert all(key in SIZE_KEYS or key in UNIT_COUNTS for key in keys), keys


def test_paper_pipeline_rehearsal(rehearsal_root, paper_data, vggt_double):
    results = run_pipeline(rehearsal_root, BUDGET)
    check_products(rehearsal_root, results, views=[3], extra=BUDGET)


@pytest.mark.slow
def test_paper_pipeline_rehearsal_at_rehearsal_budgets(tmp_path, paper_data, rehearsal_root, vggt_double):
    """The rehearsal exactly as configured (Stage 2's 20 steps, M = 50 at deployment, K = 3, 6, 9)."""
    root = fresh_root(tmp_path, rehearsal_root, paper_data)
    results = run_pipeline(root, ())
    check_products(root, results, views=[3, 6, 9], extra=())


def evaluate_out_of_domain(root: Path, mipnerf360: Path, extra: tuple[str, ...]) -> tuple[dict, Path]:
    """``tracegs-evaluate data=mipnerf360`` (Table 2) after the pipeline trained on DL3DV: no artifact named (the
    rehearsal's Mip-NeRF 360 root holds one scene of the published nine). Returns results.json and the student
    adapter it loaded."""
    overrides = ("ablation=F", "data=mipnerf360", f"data.source.root={mipnerf360}", "data.source.test_list=null",
                 *extra)
    results = run_rehearsal_task(evaluate, root, "evaluate", overrides)
    with rehearsal_job(root, "evaluate", overrides) as cfg:
        locate_artifacts(cfg, ["student_adapter"])
        return results, Path(cfg.artifacts.student_adapter)


@pytest.mark.slow
def test_the_dl3dv_student_is_evaluated_out_of_domain_at_rehearsal(tmp_path, paper_data, rehearsal_root, vggt_double):
    """Table 2 at rehearsal: after training on DL3DV, ``tracegs-evaluate data=mipnerf360`` finds the DL3DV-trained
    student (the experiment's training_data) and scores it on the Mip-NeRF 360 scene."""
    root = fresh_root(tmp_path, rehearsal_root, paper_data)
    run_pipeline(root, BUDGET)
    extra = (*BUDGET, "evaluation.methods=[tracegs]", "evaluation.save_media=false")
    results, student = evaluate_out_of_domain(root, paper_data["mipnerf360"], extra)
    trained = rehearsal_run_dir(root, "train", ("stage=stage2", "ablation=F", *BUDGET))
    assert student == trained / "student_adapter" and student.is_dir()
    assert results["meta"]["scenes"] == ["scene_100"] and results["meta"]["variant"] == "F"
    assert math.isfinite(results["tracegs"]["3"]["psnr"]) and results["tracegs"]["3"]["lpips"] > 0


TASKS = {"prepare": prepare, "train": train, "evaluate": evaluate, "report": report}


@pytest.mark.slow
def test_table_3_in_the_paper_layout_from_the_pipeline_steps_at_rehearsal(tmp_path, paper_data, rehearsal_root,
                                                                          vggt_double):
    """The ablation sweep's steps (tracegs.pipeline.steps) run in this process: one Stage-1 adapter, Stage 2 for
    B..F, every variant evaluated on DL3DV (in domain) and on Mip-NeRF 360 (out of domain) at 3, 6 and 9 views,
    then Table 3 with a column group per dataset, each cell the variant's mean over the three view counts."""
    root = fresh_root(tmp_path, rehearsal_root, paper_data)
    (root / "data" / "mipnerf360").symlink_to(paper_data["mipnerf360"])  # where data=mipnerf360 looks
    common = tuple(o for o in BUDGET if not o.startswith("evaluation.views="))
    evaluation = {"evaluation.methods": ["${ablation.method}"], "evaluation.save_media": False}
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        variants = [variant.name for variant in table3_variants()]
    steps = [Step.of("prepare", "prepare").passing(common)]
    for variant in variants:
        steps += restorer_steps(variant, evaluation=evaluation, user=common)
        # The rehearsal's Mip-NeRF 360 root holds one scene of the published nine.
        steps += out_of_domain_steps(variant, ["mipnerf360"], evaluation={**evaluation, "evaluation.scenes": ["scene_100"]},
                                     user=common)
    for step in steps:
        run_rehearsal_task(TASKS[step.app], root, step.app, step.overrides)
    table = run_rehearsal_task(report, root, "report", (*common, "report.kind=ablation"))
    lines = Path(table).read_text().splitlines()
    assert [cell.strip() for cell in lines[0].split("|")[1:-1]] == [
        "Variant", "DL3DV PSNR↑", "DL3DV SSIM↑", "DL3DV LPIPS↓", "Mip-NeRF 360 PSNR↑", "Mip-NeRF 360 SSIM↑",
        "Mip-NeRF 360 LPIPS↓"]
    rows = [[cell.strip() for cell in line.split("|")[1:-1]] for line in lines[2:] if line.startswith("|")]
    assert [row[0] for row in rows] == variants == ["A", "B", "C", "D", "E", "F-", "F"]
    assert all(math.isfinite(float(cell)) for row in rows for cell in row[1:])  # LPIPS too: required
    assert "(DL3DV: 3,6,9; Mip-NeRF 360: 3,6,9)" in Path(table).read_text()
    assert "### Mip-NeRF 360" in Path(table).with_name("table3_intervals.md").read_text()


# The two-process trainers: experiment=rehearsal keeps the paper's bf16-mixed precision on two gloo CPU ranks.
TWO_PROCESSES = {
    "ddp": ("trainer.devices=2",),  # experiment=paper's trainer
    "fsdp": ("trainer=fsdp", "trainer.devices=2"),  # the paper-scale sharding code, on CPU
}


def two_process_env(tmp_path: Path) -> dict[str, str]:
    """The console scripts' environment: the VGGT double importable, one thread per rank."""
    return {**os.environ, "PYTHONPATH": str(write_vggt_double_package(tmp_path / "doubles")),
            "OMP_NUM_THREADS": "1", "TRACEGS_TRACEBACK": "1"}


@pytest.mark.slow
@pytest.mark.parametrize("trainer", sorted(TWO_PROCESSES))
def test_paper_training_rehearsal_with_two_cpu_processes(tmp_path, paper_data, rehearsal_root, vggt_double, trainer):
    """Stage 1 and Stage 2 under the paper's DDP / FSDP configs and bf16-mixed precision with two gloo
    processes: ``tracegs-train`` as a user runs it, Lightning re-launching the command for the second rank.
    The saved adapters are whole (not one rank's shard) and float32."""
    root = fresh_root(tmp_path, rehearsal_root, paper_data)
    run_rehearsal_task(prepare, root, "prepare", BUDGET)
    script = Path(sys.executable).with_name("tracegs-train")
    for stage in ("stage=stage1", "stage=stage2"):
        command = [str(script), "experiment=rehearsal", stage, *TWO_PROCESSES[trainer], f"paths.root_dir={root}",
                   *BUDGET]
        run = subprocess.run(command, cwd=root, env=two_process_env(tmp_path), capture_output=True, text=True,
                             timeout=900)
        assert run.returncode == 0, run.stderr[-3000:]
        assert "Starting with 2 processes" in run.stdout + run.stderr
    stage1 = rehearsal_run_dir(root, "train", ("stage=stage1", *TWO_PROCESSES[trainer], *BUDGET))
    stage2 = rehearsal_run_dir(root, "train", ("stage=stage2", *TWO_PROCESSES[trainer], *BUDGET))
    shapes = {}
    for adapter in (stage1 / "stage1_adapter", stage2 / "student_adapter"):
        with safe_open(str(adapter / "adapter_model.safetensors"), framework="pt") as weights:
            tensors = {key: weights.get_tensor(key) for key in weights.keys()}  # noqa: SIM118 (safe_open)
        assert tensors and all(t.dtype == torch.float32 for t in tensors.values())
        shapes[adapter.name] = {key: tuple(t.shape) for key, t in tensors.items()}
    assert shapes["stage1_adapter"] == shapes["student_adapter"]
    rank = rehearsal_config(root).backbone.lora.rank
    assert all(rank in shape for shape in shapes["student_adapter"].values())  # whole factors, not shards


@pytest.mark.slow
@pytest.mark.parametrize("trainer", ["one-process", *sorted(TWO_PROCESSES)])
def test_ablation_sweep_script_reaches_table_3_at_rehearsal(tmp_path, paper_data, rehearsal_root, vggt_double, trainer):
    """``launch/sweep_ablation.sh local experiment=rehearsal``: A is the pretrained restorer (nothing to train),
    one Stage-1 adapter, Stage 2 for B..F, evaluation of A..F, Table 3 with every variant; in one process, and
    with every training job under the DDP / FSDP configs on two gloo CPU processes (each job of the Stage-2
    multirun launching its own second rank)."""
    root = fresh_root(tmp_path, rehearsal_root, paper_data)
    run_rehearsal_task(prepare, root, "prepare", BUDGET)
    # Table 3's out-of-domain column and Fig. 6 on Mip-NeRF 360. The sweep leaves its data settings out of the steps
    # on another dataset, so the rehearsal's Mip-NeRF 360 root (one scene, scene_100) is named in a config tree whose
    # data/mipnerf360.yaml lists that scene instead of the published nine (TRACEGS_CONF, read by every step).
    (root / "data" / "mipnerf360").symlink_to(paper_data["mipnerf360"])  # where data=mipnerf360 looks
    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf)
    listed = tmp_path / "mipnerf360_scenes.txt"
    listed.write_text("scene_100\n")
    dataset = conf / "data" / "mipnerf360.yaml"
    published = "test_list: data/scenes/mipnerf360_benchmark.txt"
    assert published in dataset.read_text()
    dataset.write_text(dataset.read_text().replace(published, f"test_list: {listed}"))
    overrides = (*TWO_PROCESSES.get(trainer, ()), *BUDGET)
    script = Path(__file__).parents[2] / "launch" / "sweep_ablation.sh"
    run = subprocess.run(["bash", str(script), "local", "experiment=rehearsal", f"paths.root_dir={root}", *overrides],
                         env={**two_process_env(tmp_path), "TRACEGS_CONF": str(conf)}, capture_output=True, text=True,
                         timeout=5400)
    assert run.returncode == 0, run.stderr[-3000:]
    if trainer in TWO_PROCESSES:
        assert (run.stdout + run.stderr).count("Starting with 2 processes") >= 1 + 6  # Stage 1, Stage 2 B..F
    (table,) = root.glob("outputs/**/table3.md")  # the report's folder, composed from the copied config tree
    lines = table.read_text().splitlines()
    rows = [line.split("|")[1].strip() for line in lines[2:] if line.startswith("|")]
    assert {"A", "B", "C", "D", "E", "F-", "F"} <= {row.split()[0].strip("()") for row in rows if row}
    assert "DL3DV PSNR↑" in lines[0] and "Mip-NeRF 360 PSNR↑" in lines[0]
    (curves,) = root.glob("outputs/**/per_step_variants.json")  # Fig. 6 on the held-out Mip-NeRF 360 clips
    assert curves.with_name("fig6_per_step_variants.png").is_file()
    assert list(root.glob("data/cache/mipnerf360-*-test-*/manifest.json"))  # prepared from the captured images


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (and gsplat)")
def test_paper_pipeline_rehearsal_on_cuda_with_gsplat(tmp_path, paper_data, rehearsal_root, vggt_double):
    root = fresh_root(tmp_path, rehearsal_root, paper_data)
    results = run_pipeline(root, (*BUDGET, *GPU))
    check_products(root, results, views=[3], extra=(*BUDGET, *GPU))
