"""The seed-replicate report states each demo figure with its mean, standard deviation and range."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tracegs.eval.seeds import demo_summary, per_step_points, seed_spread_markdown


def write_demo_run(folder: Path, seed: int, psnr_3dgs: float, psnr_tracegs: float) -> Path:
    folder.mkdir(parents=True)
    results = {"3dgs": {"3": {"psnr": psnr_3dgs, "ssim": 0.5, "lpips": None}},
               "tracegs": {"3": {"psnr": psnr_tracegs, "ssim": 0.6, "lpips": None}},
               "meta": {"lpips": "n/a", "scenes": ["scene_100"]}}
    (folder / "results.json").write_text(json.dumps(results))
    (folder / "held_out_clips.json").write_text(json.dumps({
        "conditions": {"3 views, snapshot 140": {"input": 20.0, "tracegs": 20.0 + seed}},
        "mean": {"input": 20.0, "tracegs": 20.0 + seed}, "clips": 2, "scenes": ["scene_100"]}))
    (folder / "per_step.json").write_text(json.dumps({"tracegs": [24.0, 22.0 + seed, 23.0]}))
    (folder / "run.json").write_text(json.dumps({"seed": seed, "commit": "abc", "machine": {"cpu": "x", "cores": 2}}))
    return folder


def test_per_step_points():
    assert per_step_points([24.0, 20.5, 23.3, 21.2]) == {"first": 24.0, "min": 20.5, "final": 21.2}


def test_summary_names_every_figure(tmp_path):
    summary = demo_summary(write_demo_run(tmp_path / "a", 0, 19.0, 20.0))
    assert summary["deployment PSNR"] == {"3DGS, 3 views": 19.0, "TRACE-GS, 3 views": 20.0}
    assert summary["held-out clips PSNR"]["input R_s, mean"] == 20.0
    assert summary["Fig. 6 per-step PSNR"] == {"TRACE-GS, first": 24.0, "TRACE-GS, min": 22.0,
                                               "TRACE-GS, final": 23.0}


def test_spread_over_seeds_has_mean_sd_and_range(tmp_path):
    folders = [write_demo_run(tmp_path / f"s{s}", s, 19.0 + s, 20.0 + 2 * s) for s in (0, 1, 2)]
    table = seed_spread_markdown(folders)
    row = next(line for line in table.splitlines() if line.startswith("| TRACE-GS, 3 views"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    # Values 20, 22, 24: mean 22, sample standard deviation 2, range 20..24, then each seed.
    assert cells[1:] == ["22.00", "2.00", "20.00", "24.00", "20.00", "22.00", "24.00"]
    assert "seeds (0, 1, 2)" in table


def test_a_folder_without_results_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no results.json"):
        demo_summary(tmp_path)
