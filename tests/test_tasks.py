"""Every task of tracegs/pipeline/ at the smallest size of the embedded experiment, run through its console
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
from omegaconf import OmegaConf
from safetensors import safe_open
from support.report_page import checked_page
from support.tasks import SMALLEST

# A whole demo, even at the smallest size, takes about 3 minutes on 2 cores: it runs with the other slow tests.
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def run(entry_point):
    """``tracegs-<app>`` at the smallest size with its folders under ``root`` (``extra`` overrides replace
    the smallest size's of the same key); it must succeed."""

    def run_app(app: str, root: Path, *extra: str):
        replaced = {o.split("=", 1)[0] for o in extra}
        smallest = [o for o in SMALLEST if o.split("=", 1)[0] not in replaced]
        result = entry_point(app, [f"paths.root_dir={root}", *smallest, *extra], root)
        assert result.returncode == 0, result.stderr[-3000:]
        return result

    return run_app


@pytest.fixture(scope="module")
def demo(tmp_path_factory, run) -> tuple[Path, Path, Path]:
    """(launch folder, demo folder, its held-out cache) of one smallest-size ``tracegs-demo``."""
    root = tmp_path_factory.mktemp("tasks")
    result = run("demo", root)
    folder = re.search(r"plots in (\S+)", result.stdout + result.stderr)
    assert folder, result.stdout[-2000:]
    (cache,) = (root / "data" / "cache").glob("synthetic-tiny-test-*")
    return root, Path(folder.group(1)), cache


@pytest.fixture
def held_out(demo) -> tuple[str, ...]:
    """The overrides that point a report at the demo's held-out cache (quoted: run folders hold ',' and '=')."""
    return "data.prepare.split=test", f"evaluation.held_out_cache='{demo[2]}'"


def test_demo_runs_every_step_and_writes_its_tables(demo):
    out = demo[1]
    run_record = json.loads((out / "run.json").read_text())
    assert list(run_record["step_s"]) == ["prepare (training scenes)", "prepare (held-out test scenes)", "train A",
                                          "train Stage 1", "train Stage 2", "evaluate"]
    results = json.loads((out / "results.json").read_text())
    assert set(results) >= {"3dgs", "baseline", "tracegs"} and set(results["tracegs"]) == {"3"}
    held_out = json.loads((out / "held_out_clips.json").read_text())  # tasks.held_out_quality
    assert set(held_out["mean"]) == {"input", "baseline", "tracegs"} and held_out["clips"] == 1
    assert "Deployment on the test scenes" in (out / "tables.md").read_text()
    text, links = checked_page(out, "tables.md")
    assert "fig6_per_step.png" in links and any(link.endswith("_trajectory.mp4") for link in links)
    assert run_record["commit"] in text


def test_the_demo_models_evaluate_on_other_test_scenes_without_naming_them(demo, run):
    """``tracegs-evaluate data.synthetic.test_seeds=[...]`` after the demo finds the demo's A and student (a trained
    model is named by its training scenes, never by a test list) and evaluates them on the new scene."""
    root = demo[0]
    run("evaluate", root, "ablation=F", "data.synthetic.test_seeds=[102]", "evaluation.methods=[baseline,tracegs]",
        "evaluation.save_media=false")
    evaluations = [json.loads(p.read_text()) for p in root.glob("outputs/embedded/eval/F/synthetic-*/results.json")]
    (results,) = [r for r in evaluations if r["meta"]["scenes"] == ["scene_102"]]
    for method in ("baseline", "tracegs"):
        assert results[method]["3"]["psnr"] > 0


def test_the_last_shard_of_a_prepare_merges_the_manifests(demo, run):
    """A shard that finds another unfinished leaves the cache without its manifest; the last one writes it: the
    first shard's settings and both shards' scenes in name order."""
    root = demo[0]
    held_out = ("data.prepare.split=test", "data.synthetic.test_seeds=[100,101]", "data.prepare.num_shards=2")
    first = run("prepare", root, *held_out, "data.prepare.shard_index=0")
    (cache,) = {p.parent for p in root.rglob("manifest_shard*_of002.json")}
    assert not (cache / "manifest.json").exists() and "1 of 2 shards still to finish" in first.stdout + first.stderr
    run("prepare", root, *held_out, "data.prepare.shard_index=1")
    shards = [json.loads((cache / f"manifest_shard{i:03d}_of002.json").read_text()) for i in (0, 1)]
    merged = {**{k: v for k, v in shards[0].items() if k != "scenes"},
              "scenes": dict(sorted({**shards[0]["scenes"], **shards[1]["scenes"]}.items()))}
    assert (cache / "manifest.json").read_text() == json.dumps(merged, indent=2) + "\n"
    assert list(merged["scenes"]) == ["scene_100", "scene_101"]


def test_report_privileged_restores_from_both_view_sets(demo, run, entry_point, tmp_path):
    """The demo's held-out cache has no teacher R_d, and the report says so; prepared with the teacher, it runs."""
    root, caches = demo[0], demo[0] / "data" / "cache"
    with safe_open(str(next(demo[2].rglob("clip_000.safetensors"))), framework="pt") as f:
        assert not [k for k in f.keys() if k.startswith("latent/d")]
    report = ("report.kind=privileged", "data.prepare.split=test", f"report.output_dir={tmp_path}")
    failed = entry_point("report", [f"paths.root_dir={root}", *SMALLEST, *report,
                                    f"evaluation.held_out_cache='{demo[2]}'"], root)
    assert failed.returncode != 0 and "no teacher condition dall" in failed.stderr, failed.stderr[-2000:]
    before = set(caches.glob("synthetic-tiny-test-*"))
    run("prepare", root, "data.prepare.split=test", "data.prepare.student_views=[3]")
    (with_teacher,) = set(caches.glob("synthetic-tiny-test-*")) - before
    run("report", root, *report, f"evaluation.held_out_cache='{with_teacher}'")
    gap = json.loads((tmp_path / "privileged_gap.json").read_text())
    assert gap and (tmp_path / "privileged_gap.md").read_text().strip()


def test_report_per_step_compares_the_trained_variants(demo, held_out, run, tmp_path):
    root = demo[0]
    run("report", root, "report.kind=per_step", "report.inputs=[A,F]", *held_out, f"report.output_dir={tmp_path}")
    curves = json.loads((tmp_path / "per_step_variants.json").read_text())
    assert set(curves) == {"A", "F"} and all(len(c) == 5 for c in curves.values())  # one value per reverse step
    assert (tmp_path / "fig6_per_step_variants.png").is_file()
    breakdown = (tmp_path / "per_step_breakdown.md").read_text()  # synthetic clips: rendered, never padded
    assert "| all | mean over K |" in breakdown and "| padded | mean over K | 0 |" in breakdown


def test_report_seeds_spreads_demo_runs(demo, run, tmp_path):
    root, out = demo[:2]
    run("report", root, "report.kind=seeds", f"report.inputs=['{out}','{out}']", f"report.output_dir={tmp_path}")
    assert "|" in (tmp_path / "seeds.md").read_text()


def test_optuna_chooses_stage2s_learning_rate_on_the_validation_scenes(demo, run, entry_point):
    """``conf/hparams_search/stage2_lr.yaml`` through the Optuna sweeper: each trial trains its own Stage 2 on the
    demo's A and Stage 1 and returns its held-out clip PSNR on the validation cache; the sweeper reports the best."""
    root = demo[0]
    run("prepare", root, "data.prepare.split=val")
    search = entry_point("train", ["-m", f"paths.root_dir={root}", *SMALLEST, "stage=stage2", "hparams_search=stage2_lr",
                                   "hydra.sweeper.n_trials=2"], root)
    assert search.returncode == 0, search.stderr[-3000:]
    (results,) = root.glob("outputs/embedded/multirun/*/optimization_results.yaml")
    best = OmegaConf.load(results)
    trials = {}
    for curve in root.glob("outputs/embedded/stage2/F/*/held_out_curve.json"):
        lr = OmegaConf.load(curve.parent / "config.yaml").experiment.stage2_lr
        trials[lr] = json.loads(curve.read_text())["points"][-1]["mean"]
    assert len(trials) == 2
    assert best.best_value == max(trials.values())
    assert trials[best.best_params["experiment.stage2_lr"]] == best.best_value


def test_replicate_measures_table3_at_its_smallest_size(run, tmp_path_factory):
    """``tracegs-replicate`` (make replicate) at its smallest size, two variants on two test scenes with one
    training seed: every step runs as a child command, and the report holds Table 3, the orderings, both
    diagnostics and Fig. 6, its JSON record the wall time and the F - A interval."""
    root = tmp_path_factory.mktemp("replicate")
    result = run("replicate", root, "replicate.training_seeds=[0]", "replicate.held_out_clips_per_scene=1",
                 "replicate.variants=[A,F]", "data.synthetic.test_seeds=[100,101]")
    (report,) = root.rglob("replicate.md")
    text = report.read_text()
    assert "## Table 3 (deployment)" in text and "training seeds [0]" in text and "## Exposure gap" in text
    assert "## Teacher advantage at the student's states" in text and "## Fig. 6" in text
    assert "| (A) |" in text and "| (F) |" in text and "| 3DGS |" in text
    assert "| (B) < (A) | PSNR↑ | 3 |  | **not measured** |" in text  # B was not run
    assert "(A) < (F)" in text and "**not resolved**" in text  # two scenes resolve nothing
    assert re.search(r"wall time \d+\.\d min", text)
    assert {p.name for p in report.parent.glob("per_scene_seed*.csv")} == {"per_scene_seed0.csv",
                                                                            "per_scene_seed_mean.csv"}
    assert (report.parent / "fig6_per_step.png").is_file()
    record = json.loads((report.parent / "run.json").read_text())
    assert record["training_seeds"] == [0] and record["variants"] == ["A", "F"]
    assert record["table3_minutes"] > 0 and record["f_minus_a_3views_half_width_db"] >= 0
    # Data twice, plain 3DGS once; A, Stage 1, the students' multirun, the evaluations' and the diagnostics.
    assert len(record["step_s"]) == 3 + 5
    assert text.strip() in result.stdout
    _, links = checked_page(report.parent, "replicate.md")
    assert {"eval/3dgs/report.html", "eval/seed0/A/report.html", "eval/seed0/F/report.html"} <= set(links)
