"""The benchmark's report assembles from several training seeds' results, sharing plain 3DGS."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from tracegs.eval.replicates import instrument_line, mean_tree, write_benchmark_report
from tracegs.io import write_json_atomic

SCENES = [f"scene_{100 + i}" for i in range(8)]
CONTENT = [0.0, 1.5, -2.0, 0.7, 2.4, -1.1, 0.3, -0.6]


def _row(psnr: float) -> dict:
    return {"psnr": psnr, "ssim": 0.5, "lpips": None}


def write_seed(root: Path, seed: int) -> tuple[Path, Path]:
    """One training seed's evaluation (3DGS only in seed 0's) and privileged-gap folders. TRACE-GS - A is
    0.3 + 0.1 * seed on every scene; A - 3DGS is +1.0."""
    eval_dir, gap_dir = root / "eval" / f"seed{seed}", root / "privileged" / f"seed{seed}"
    per_scene = {}
    for scene, content in zip(SCENES, CONTENT):
        methods = {"baseline": {"3": _row(19.0 + content)}, "tracegs": {"3": _row(19.3 + content + 0.1 * seed)}}
        if seed == 0:
            methods["3dgs"] = {"3": _row(18.0 + content)}
        per_scene[scene] = methods
        write_json_atomic({"scene": scene, "views": 3, "per_step": {"baseline": [15.0, 16.0 + content],
                                                                    "tracegs": [15.0, 16.5 + content]}},
                          eval_dir / "units" / scene / "views_3.json")
    write_json_atomic(per_scene, eval_dir / "per_scene.json")
    held_out = {scene: {"s3_it140": {"input": 20.0 + c, "baseline": 20.2 + c, "tracegs": 20.1 + c + seed}}
                for scene, c in zip(SCENES, CONTENT)}
    write_json_atomic({"conditions": {"s3_it140": {"input": 20.0, "baseline": 20.2, "tracegs": 20.1 + seed}},
                       "mean": {"input": 20.0, "baseline": 20.2, "tracegs": 20.1 + seed}, "clips": 16,
                       "scenes": SCENES, "per_scene": held_out}, eval_dir / "held_out_clips.json")
    gap = {scene: {"input R_d": {"gt": 24.0 + c}, "input R_s": {"gt": 20.0 + c, "R_d": 21.0 + c},
                   "tracegs | R_d": {"gt": 23.0 + c, "R_d": 25.0 + c},
                   "tracegs | R_s": {"gt": 20.5 + c, "R_d": 21.5 + c}} for scene, c in zip(SCENES, CONTENT)}
    write_json_atomic({"per_scene": gap, "rows": list(gap[SCENES[0]]), "teacher": "dall", "clips": 16,
                       "conditions": ["s3_it140", "s3_it340"]},
                      gap_dir / "privileged_gap.json")
    return eval_dir, gap_dir


def test_mean_tree_averages_leaves_and_keeps_labels():
    trees = [{"a": {"x": 1.0, "c": [1.0, 3.0], "n": None, "s": "k"}}, {"a": {"x": 3.0, "c": [3.0, 5.0], "n": None,
                                                                             "s": "k"}}]
    assert mean_tree(trees) == {"a": {"x": 2.0, "c": [2.0, 4.0], "n": None, "s": "k"}}


def test_report_assembles_from_three_seeds(tmp_path):
    folders = [write_seed(tmp_path, seed) for seed in (0, 1, 2)]
    path = write_benchmark_report(tmp_path / "report", [0, 1, 2], [f[0] for f in folders],
                                  [f[1] for f in folders], header="# Embedded benchmark\n")
    text = path.read_text()
    # Seeds averaged per scene: TRACE-GS - A = 0.4 on every scene, so a zero-width interval.
    assert "Instrument: the 95% interval of TRACE-GS − A at 3 views is +0.40 [+0.40, +0.40] dB, half-width ±0.00" \
           in text and "target ≤ ±0.2 dB: met" in text
    # Next to it, the spread over seeds: 0.3, 0.4, 0.5 (sd 0.1), and no spread over scenes.
    row = next(line for line in text.splitlines() if line.startswith("| TRACE-GS − A | 3 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:6] == ["+0.30", "+0.40", "+0.50", "0.10"]
    assert cells[7] == "0.00"
    # Plain 3DGS, evaluated only by seed 0, is shared by every seed: A - 3DGS = +1.0 on each.
    assert "| A − 3DGS | 3 | +1.00 | +1.00 | +1.00 | 0.00 |" in text
    rows = list(csv.DictReader((tmp_path / "report" / "per_scene_seed2.csv").open()))
    assert {r["method"] for r in rows} == {"3dgs", "baseline", "tracegs"}
    # Held-out clips (TRACE-GS gains seed dB: mean +1 over seeds), Fig. 6 with bands, the privileged gap.
    assert "| TRACE-GS − A | +0.90 [+0.90, +0.90] | +0.90 [+0.90, +0.90] |" in text
    assert (tmp_path / "report" / "fig6_per_step.png").is_file()
    assert "| TRACE-GS − A |" in (tmp_path / "report" / "per_step_intervals.md").read_text()
    assert "| Stage-2 student (TRACE-GS) | +2.50 [+2.50, +2.50] |" in text
    # The report ends with the orderings marked.
    conclusions = text[text.index("## Conclusions"):]
    assert "- TRACE-GS > Baseline (A), 3 views, PSNR: **holds** (+0.40 [+0.40, +0.40])" in conclusions
    assert "- Baseline (A) > 3DGS, 3 views, PSNR: **holds** (+1.00 [+1.00, +1.00])" in conclusions


def test_the_instrument_is_not_judged_on_too_few_scenes():
    per_scene = {s: {"baseline": {"3": _row(19.0 + c)}, "tracegs": {"3": _row(19.3 + c)}}
                 for s, c in zip(SCENES[:2], CONTENT)}
    assert "not assessable from 2 scenes, fewer than 6" in instrument_line(per_scene)


def test_a_missing_seed_result_is_named(tmp_path):
    eval_dir, gap_dir = write_seed(tmp_path, 0)
    with pytest.raises(FileNotFoundError, match="seed1/per_scene.json is missing"):
        write_benchmark_report(tmp_path / "report", [0, 1], [eval_dir, tmp_path / "eval" / "seed1"], [gap_dir])
