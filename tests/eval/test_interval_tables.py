"""The report's tables with intervals: per-scene CSV, paired differences and the orderings marked."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from tracegs.eval.interval_tables import held_out_intervals_markdown
from tracegs.eval.merge import merge_results, unit_path
from tracegs.eval.tables_and_figures import held_out_table_markdown, write_ablation_report
from tracegs.io import write_json_atomic

SCENES = [f"scene_{100 + i}" for i in range(6)]
CONTENT = [0.0, 3.1, -2.4, 1.7, -0.8, 2.2]  # scene difficulty, shared by every method


def _unit(scene: str, views: int, psnr: dict[str, float]) -> dict:
    methods = {m: {"per_view": [{"psnr": v, "ssim": 0.5, "lpips": None}],
                   "mean": {"psnr": v, "ssim": 0.5, "lpips": None}} for m, v in psnr.items()}
    return {"scene": scene, "views": views, "lpips": "LPIPS n/a", "methods": methods,
            "per_step": {"baseline": [15.0 + views, 16.0], "tracegs": [15.0, 17.0 + CONTENT[SCENES.index(scene)]]}}


def test_merge_writes_per_scene_csv_intervals_and_conclusions(tmp_path):
    for scene, content in zip(SCENES, CONTENT):
        for k in (3, 6):
            # TRACE-GS beats A by exactly 0.4 dB on every scene; A and 3DGS alternate by +-0.3 dB.
            noise = 0.3 if SCENES.index(scene) % 2 else -0.3
            write_json_atomic(_unit(scene, k, {"3dgs": 15.0 + content, "baseline": 15.0 + content + noise,
                                               "tracegs": 15.4 + content + noise}), unit_path(tmp_path, scene, k))
    merge_results(tmp_path)
    rows = list(csv.DictReader((tmp_path / "per_scene.csv").open()))
    assert len(rows) == len(SCENES) * 2 * 3
    row = next(r for r in rows if r["scene"] == "scene_101" and r["views"] == "6" and r["method"] == "tracegs")
    assert float(row["psnr"]) == 15.4 + 3.1 + 0.3
    text = (tmp_path / "intervals.md").read_text()
    assert "| A − 3DGS | +0.00 [" in text
    assert "- TRACE-GS > Baseline (A), 3 views, PSNR: **holds** (+0.40 [+0.40, +0.40])" in text
    assert "- Baseline (A) > 3DGS, 6 views, PSNR: **not resolved**" in text
    # SSIM is equal everywhere: a zero-width interval at 0 resolves nothing.
    assert "- TRACE-GS > Baseline (A), 3 views, SSIM: **not resolved** (+0.000 [+0.000, +0.000])" in text
    assert "LPIPS" not in text  # no LPIPS values: no LPIPS column, nothing invented
    steps = list(csv.DictReader((tmp_path / "per_step_per_scene.csv").open()))
    assert len(steps) == len(SCENES) * 2 * 2 * 2
    assert (tmp_path / "fig6_per_step.png").is_file()
    per_step = (tmp_path / "per_step_intervals.md").read_text()
    # Step 1: TRACE-GS 15 vs A 15 + K (K = 3, 6 averaged within each scene): -4.5 on every scene.
    assert "| 1 | 19.50 [19.50, 19.50] | 15.00 [15.00, 15.00] | -4.50 [-4.50, -4.50] |" in per_step


def _variant_folder(root: Path, variant: str, shift: float) -> Path:
    folder = root / variant
    method = "baseline" if variant == "A" else "tracegs"
    per_scene = {scene: {method: {k: {"psnr": 18.0 + content + shift + (0.1 if k == "3" else -0.1),
                                      "ssim": 0.6, "lpips": None} for k in ("3", "9")}}
                 for scene, content in zip(SCENES, CONTENT)}
    results = {method: {k: {"psnr": 18.0 + shift, "ssim": 0.6, "lpips": None} for k in ("3", "9")},
               "meta": {"variant": variant, "lpips": "n/a"}}
    write_json_atomic(results, folder / "results.json")
    write_json_atomic(per_scene, folder / "per_scene.json")
    return folder


def test_ablation_table_marks_the_orderings(tmp_path):
    shifts = {"A": 0.0, "B": -0.3, "E": 0.2, "F-": 0.1, "F": 0.5}
    folders = [_variant_folder(tmp_path / "eval", v, s) for v, s in shifts.items()]
    write_ablation_report({"synthetic": folders}, tmp_path / "report")
    text = (tmp_path / "report" / "table3_intervals.md").read_text()
    # Scene content averages 0.633 dB; the two view counts cancel (+-0.1).
    assert "| F | 19.13 [" in text and "| +0.50 [+0.50, +0.50] |" in text
    assert "- A > B, PSNR: **holds** (+0.30 [+0.30, +0.30])" in text
    assert "- C > A, PSNR: **not measured**" in text
    assert "- F- > E, PSNR: **reversed** (-0.10 [-0.10, -0.10])" in text
    assert "- F > F-, PSNR: **holds** (+0.40 [+0.40, +0.40])" in text
    rows = list(csv.DictReader((tmp_path / "report" / "table3_synthetic_per_scene.csv").open()))
    assert {r["variant"] for r in rows} == set(shifts)
    f_row = next(r for r in rows if r["scene"] == "scene_101" and r["views"] == "9" and r["variant"] == "F")
    assert float(f_row["psnr"]) == 18.0 + 3.1 + 0.5 - 0.1
    assert len(rows) == len(SCENES) * 2 * len(shifts)


def test_held_out_intervals_pair_scene_and_condition():
    conditions = ["3 views, snapshot 140", "6 views, snapshot 140"]
    per_scene = {scene: {cond: {"input": 20.0 + content + i, "baseline": 19.8 + content + i,
                                "tracegs": 20.1 + content + i} for i, cond in enumerate(conditions)}
                 for scene, content in zip(SCENES, CONTENT)}
    mean = {label: sum(per_scene[s][c][label] for s in SCENES for c in conditions) / 12
            for label in ("input", "baseline", "tracegs")}
    quality = {"conditions": {c: {label: sum(per_scene[s][c][label] for s in SCENES) / 6 for label in mean}
                              for c in conditions},
               "mean": mean, "clips": 12, "scenes": SCENES, "per_scene": per_scene}
    text = held_out_intervals_markdown(quality)
    assert "| A − input R_s | -0.20 [-0.20, -0.20] | -0.20 [-0.20, -0.20] | -0.20 [-0.20, -0.20] |" in text
    assert "| TRACE-GS − A | +0.30 [+0.30, +0.30]" in text
    assert text in held_out_table_markdown(quality)
    json.dumps(quality)  # the layout stays JSON (held_out_clips.json)
