"""Every task of tracegs/tasks.py at the smallest size of the embedded experiment, run through its console
script (tracegs.cli.app) as a user runs it.

``tracegs-demo`` runs prepare (train and held-out splits), the three training stages and the evaluation
with the held-out clip quality; the report kinds then read what it made. Deployment and ``report.kind=main``
at the smallest paper-shaped size are in tests/rehearsal/test_paper_pipeline.py, ``tracegs-restore`` in
tests/deploy/test_restore_capture.py, the ablation sweep (``report.kind=ablation``) in the slow sweep test.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

# Counts only (steps, clips, scenes, iterations, reverse steps): every mode stays the embedded default's.
SMALLEST = (
    "experiment.baseline_steps=1",
    "experiment.stage1_steps=1",
    "experiment.stage2_steps=1",
    "experiment.stage2_warmup_steps=0",
    "experiment.clips_per_scene=1",
    "experiment.batch_size=1",
    "data.synthetic.train_seeds=[0]",
    "data.synthetic.test_seeds=[100]",
    "data.synthetic.val_seeds=[50]",
    "data.prepare.fit.iterations=20",
    "data.prepare.fit.snapshot_iters=[5,10,20]",
    "deploy.total_iters=20",
    "deploy.repair_iters=[5,10,15]",
    "deploy.max_clips_per_round=1",
    "evaluation.views=[3]",
    "backbone.schedule.deploy_steps=5",  # M = the embedded Stage-2 rollout N (a stage's own setting)
)


@pytest.fixture(scope="module")
def run(entry_point):
    """``tracegs-<app>`` at the smallest size with its folders under ``root``; it must succeed."""

    def run_app(app: str, root: Path, *extra: str):
        result = entry_point(app, [f"paths.root_dir={root}", *SMALLEST, *extra], root)
        assert result.returncode == 0, result.stderr[-3000:]
        return result

    return run_app


@pytest.fixture(scope="module")
def demo(tmp_path_factory, run) -> tuple[Path, Path]:
    """(launch folder, demo folder) of one smallest-size ``tracegs-demo``."""
    root = tmp_path_factory.mktemp("tasks")
    result = run("demo", root)
    folder = re.search(r"plots in (\S+)", result.stdout + result.stderr)
    assert folder, result.stdout[-2000:]
    return root, Path(folder.group(1))


def test_demo_runs_every_step_and_writes_its_tables(demo):
    _, out = demo
    run_record = json.loads((out / "run.json").read_text())
    assert list(run_record["step_s"]) == ["prepare", "prepare data.prepare.split=test", "train stage=baseline",
                                          "train stage=stage1", "train stage=stage2 ablation=F",
                                          "evaluate ablation=F data.prepare.split=test"]
    results = json.loads((out / "results.json").read_text())
    assert set(results) >= {"3dgs", "baseline", "tracegs"} and set(results["tracegs"]) == {"3"}
    held_out = json.loads((out / "held_out_clips.json").read_text())  # tasks.held_out_quality
    assert set(held_out["mean"]) == {"input", "baseline", "tracegs"} and held_out["clips"] == 1
    assert "Deployment on the test scenes" in (out / "tables.md").read_text()


def test_report_prepare_merges_the_cache_manifest(demo, run):
    root, _ = demo
    result = run("report", root, "report.kind=prepare")
    manifests = list(root.rglob("manifest.json"))
    assert manifests and all(json.loads(m.read_text())["scenes"] for m in manifests), result.stdout


def test_report_privileged_restores_from_both_view_sets(demo, run, tmp_path):
    root, _ = demo
    run("report", root, "report.kind=privileged", "data.prepare.split=test",
        "evaluation.held_out_cache=${data.prepare.cache_dir}", f"report.output_dir={tmp_path}")
    gap = json.loads((tmp_path / "privileged_gap.json").read_text())
    assert gap and (tmp_path / "privileged_gap.md").read_text().strip()


def test_report_per_step_compares_the_trained_variants(demo, run, tmp_path):
    root, _ = demo
    run("report", root, "report.kind=per_step", "report.inputs=[A,F]", "data.prepare.split=test",
        "evaluation.held_out_cache=${data.prepare.cache_dir}", f"report.output_dir={tmp_path}")
    curves = json.loads((tmp_path / "per_step_variants.json").read_text())
    assert set(curves) == {"A", "F"} and all(len(c) == 5 for c in curves.values())  # one value per reverse step
    assert (tmp_path / "fig6_per_step_variants.png").is_file()


def test_report_seeds_spreads_demo_runs(demo, run, tmp_path):
    root, out = demo
    run("report", root, "report.kind=seeds", f"report.inputs=[{out},{out}]", f"report.output_dir={tmp_path}")
    assert "|" in (tmp_path / "seeds.md").read_text()
