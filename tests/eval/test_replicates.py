"""tracegs-replicate's report: Table 3's variants over training seeds, the orderings marked, both trajectory
diagnostics and Fig. 6, assembled from the per-seed results tracegs-replicate's steps write."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from tracegs.eval.replicates import (
    ReplicateInputs,
    diagnostics_markdown,
    instrument,
    label,
    mean_tree,
    write_replicate_report,
)
from tracegs.io import write_json_atomic

SCENES = [f"scene_{100 + i}" for i in range(8)]
CONTENT = [0.0, 1.5, -2.0, 0.7, 2.4, -1.1, 0.3, -0.6]
VARIANTS = ["A", "B", "E", "F-", "F"]
# Each variant's offset over A (dB PSNR): B below A, E < F- < F; seed s adds 0.1 * s to every student.
OFFSET = {"A": 0.0, "B": -0.2, "E": 0.1, "F-": 0.2, "F": 0.3}
STEPS = 3


def _row(psnr: float) -> dict:
    return {"psnr": psnr, "ssim": 0.5, "lpips": None}


def _diagnostics(variant: str, content: float, seed: int) -> dict:
    """Per-step curves: the visited state 0.5 dB above the forward-noised one after step 1, except for E
    (the same states); the teacher 1 dB above the student; the final sample at the last visited value."""
    learned = OFFSET[variant] + (0.1 * seed if variant != "A" else 0.0)
    visited = [15.0 + content, 16.0 + content, 17.0 + content + learned]
    gap = 0.0 if variant in ("A", "E") else 0.5
    return {"visited": visited, "noised": [visited[0]] + [v - gap for v in visited[1:]],
            "teacher": None if variant == "A" else [v + 1.0 for v in visited], "final": visited[-1],
            "input": 16.5 + content}


def write_run(root: Path, seeds: list[int]) -> ReplicateInputs:
    """A tracegs-replicate run's results: plain 3DGS once, every variant's deployment and the diagnostics per seed."""
    write_json_atomic({s: {"3dgs": {"3": _row(18.0 + c)}} for s, c in zip(SCENES, CONTENT)},
                      root / "eval" / "3dgs" / "per_scene.json")
    for seed in seeds:
        for variant in VARIANTS:
            method, shift = ("baseline", 0.0) if variant == "A" else ("tracegs", OFFSET[variant] + 0.1 * seed)
            write_json_atomic({s: {method: {"3": _row(19.0 + c + shift)}} for s, c in zip(SCENES, CONTENT)},
                              root / "eval" / f"seed{seed}" / variant / "per_scene.json")
        write_json_atomic({"per_scene": {s: {v: _diagnostics(v, c, seed) for v in VARIANTS}
                                         for s, c in zip(SCENES, CONTENT)},
                           "conditions": ["s3_it140", "s3_it340"], "clips": 16, "steps": STEPS},
                          root / "diagnostics" / f"seed{seed}" / "diagnostics.json")
    return ReplicateInputs(seeds=seeds, variants=VARIANTS, descriptions={v: f"variant {v}" for v in VARIANTS},
                           methods={v: "baseline" if v == "A" else "tracegs" for v in VARIANTS},
                           eval_dirs={s: root / "eval" / f"seed{s}" for s in seeds},
                           three_dgs_dir=root / "eval" / "3dgs",
                           diagnostics_dirs={s: root / "diagnostics" / f"seed{s}" for s in seeds})


def _cells(text: str, start: str) -> list[str]:
    row = next(line for line in text.splitlines() if line.startswith(start))
    return [c.strip() for c in row.strip("|").split("|")]


def test_mean_tree_averages_leaves_and_keeps_labels():
    trees = [{"a": {"x": 1.0, "c": [1.0, 3.0], "n": None, "s": "k"}}, {"a": {"x": 3.0, "c": [3.0, 5.0], "n": None,
                                                                             "s": "k"}}]
    assert mean_tree(trees) == {"a": {"x": 2.0, "c": [2.0, 4.0], "n": None, "s": "k"}}


def test_variants_are_named_as_in_the_paper():
    assert [label(v) for v in ("A", "F-", "F", "3dgs")] == ["(A)", "(F⁻)", "(F)", "3DGS"]


def test_report_assembles_table3_from_three_seeds(tmp_path):
    path, figures = write_replicate_report(tmp_path / "report", write_run(tmp_path, [0, 1, 2]),
                                           header="# Table 3 replicated over training seeds (embedded scale)\n")
    text = path.read_text()
    # Seeds averaged per scene: F - A = 0.3 + 0.1 (mean seed offset) on every scene, a zero-width interval.
    assert "the 95% interval of (F) − (A) at 3 views is +0.40 [+0.40, +0.40] dB" in text and "met" in text
    assert figures["f_minus_a_3views_half_width_db"] == 0.0
    assert figures["f_minus_a_3views_db"] == [0.4, 0.4, 0.4]
    # Each variant's row: its mean per seed and their spread, its difference to A; plain 3DGS shared.
    assert _cells(text, "| (F) |")[2:5] == ["19.45 / 19.55 / 19.65", "0.10", "+0.40 [+0.40, +0.40]"]
    assert _cells(text, "| (B) |")[4] == "-0.10 [-0.10, -0.10]"
    assert _cells(text, "| 3DGS |")[2:4] == ["18.15 / 18.15 / 18.15", "0.00"]
    # Every ordering of Tables 1-3 is marked; C and D were not run.
    assert _cells(text, "| (B) < (A) | PSNR↑ | 3 |")[3:5] == ["+0.10 [+0.10, +0.10]", "**holds**"]
    assert _cells(text, "| (E) < (F⁻) | PSNR↑ | 3 |")[3:6] == ["+0.10 [+0.10, +0.10]", "**holds**",
                                                             "+0.10 / +0.10 / +0.10"]
    assert _cells(text, "| (A) < (C) | PSNR↑ | 3 |")[4] == "**not measured**"
    assert _cells(text, "| 3DGS < (A) | PSNR↑ | 3 |")[4] == "**holds**"
    assert figures["orderings"]["(F⁻) < (F), PSNR, 3 views"] == "holds"
    assert len([k for k in figures["orderings"] if k.endswith("PSNR, 3 views")]) == 7
    # Held-out clips, Fig. 6 (A, E, F), the exposure gap (0 at step 1; 0.5 later except A and E) and the
    # teacher advantage (1 dB for the distilled variants).
    held_out = text[text.index("## Held-out clips"):]
    assert _cells(held_out, "| (F) | ")[2:] == ["+0.90 [+0.90, +0.90]", "+0.40 [+0.40, +0.40]"]
    assert _cells(held_out, "| (F) | ")[1].startswith("17.55 [")
    assert (tmp_path / "report" / "fig6_per_step.png").is_file()
    fig6 = (tmp_path / "report" / "per_step_intervals.md").read_text()
    assert "| step | (A) | (E) | (F) | (F) − (E) | (F) − (A) |" in fig6
    assert "(A) variant A; (B) variant B;" in text
    gap = text[text.index("## Exposure gap"):text.index("## Teacher advantage")]
    assert _cells(gap, "| step |") == ["step", "(A)", "(B)", "(E)", "(F⁻)", "(F)"]
    assert _cells(gap, "| 1 |")[1:] == ["+0.00 [+0.00, +0.00]"] * 5
    none, half = "+0.00 [+0.00, +0.00]", "+0.50 [+0.50, +0.50]"
    assert _cells(gap, "| mean of steps 2+ |")[1:] == [none, half, none, half, half]
    assert "(B) step 2" in gap and "(E) step 2" not in gap
    assert figures["exposure_gap_largest_db"] == 0.5
    # The later half of the trajectory (steps 2-3 of 3): the gap of each variant with its interval over scenes.
    assert _cells(gap, "| mean of steps 2-3 (later half) |")[1:] == [none, half, none, half, half]
    assert figures["exposure_gap_late_db"]["F"] == [0.5, 0.5, 0.5]
    assert figures["exposure_gap_late_db"]["E"] == [0.0, 0.0, 0.0]
    # A on the held-out clips: final 17 + c against input 16.5 + c and against its first prediction 15 + c.
    assert figures["a_minus_input_db"] == [0.5, 0.5, 0.5]
    assert figures["trajectory_final_minus_first_db"] == [2.0, 2.0, 2.0]
    # The students F (+0.3) and B (-0.2) lie 0.5 dB apart; each student's seed means move by 0.1 per seed.
    assert figures["students_spread_db"]["3"] == {"largest_difference": 0.5, "between": ["F", "B"], "seed_sd": 0.1}
    advantage = text[text.index("## Teacher advantage"):]
    assert _cells(advantage, "| step |") == ["step", "(B)", "(E)", "(F⁻)", "(F)"]
    assert _cells(advantage, "| 2 |")[1:] == ["+1.00 [+1.00, +1.00]"] * 4
    rows = list(csv.DictReader((tmp_path / "report" / "per_scene_seed2.csv").open()))
    assert {r["variant"] for r in rows} == {"3dgs", *VARIANTS}


def test_the_instrument_is_not_judged_on_too_few_scenes():
    per_scene = {s: {"A": {"3": _row(19.0 + c)}, "F": {"3": _row(19.3 + c)}} for s, c in zip(SCENES[:2], CONTENT)}
    line, gap = instrument(per_scene, "3")
    assert "not assessable from 2 scenes, fewer than 6" in line and gap.n == 2


def test_a_missing_seed_result_is_named(tmp_path):
    inputs = write_run(tmp_path, [0])
    inputs.seeds, inputs.eval_dirs[1] = [0, 1], tmp_path / "eval" / "seed1"
    with pytest.raises(FileNotFoundError, match="seed1/A/per_scene.json is missing"):
        write_replicate_report(tmp_path / "report", inputs)
    assert not (tmp_path / "report" / "replicate.md").exists()
    assert json.loads((tmp_path / "eval" / "seed0" / "F" / "per_scene.json").read_text())


def test_one_seeds_diagnostics_are_summarised_with_the_mechanism_figures():
    """``tracegs-report report.kind=diagnostics``: each variant's first prediction, final - first and later-half
    exposure gap with intervals over scenes, then the run record's figures as one JSON line."""
    diagnostics = {"per_scene": {s: {v: _diagnostics(v, c, 0) for v in ("A", "F")} for s, c in zip(SCENES, CONTENT)},
                   "conditions": ["s3_it140"], "clips": 8, "steps": STEPS}
    text = diagnostics_markdown(diagnostics, ["A", "F"])
    assert _cells(text, "| (A) | 15")[2:] == ["+2.00 [+2.00, +2.00]", "+0.00 [+0.00, +0.00]"]
    assert _cells(text, "| (F) | 15")[2:] == ["+2.30 [+2.30, +2.30]", "+0.50 [+0.50, +0.50]"]  # F learned +0.3
    figures = json.loads(text.strip().splitlines()[-1])
    assert figures["a_minus_input_db"] == [0.5, 0.5, 0.5] and figures["exposure_gap_late_db"]["F"] == [0.5, 0.5, 0.5]


def test_the_students_are_set_against_the_stage1_adapter_they_start_from():
    """``report.stage1_row``: the Stage-1 adapter is a row of its own and each student's final sample is paired
    with it over scenes (here the adapter scores as A, and F learned +0.3 dB from it)."""
    diagnostics = {"per_scene": {s: {"A": _diagnostics("A", c, 0), "stage1": _diagnostics("A", c, 0),
                                     "F": _diagnostics("F", c, 0)} for s, c in zip(SCENES, CONTENT)},
                   "conditions": ["s3_it140"], "clips": 8, "steps": STEPS}
    text = diagnostics_markdown(diagnostics, ["stage1", "A", "F"], start="stage1")
    assert "| variant | restored [95% CI over scenes] | − input R_s | − (A) | − Stage-1 adapter |" in text
    assert _cells(text, "| (F) | 1")[3:] == ["+0.30 [+0.30, +0.30]", "+0.30 [+0.30, +0.30]"]
    assert _cells(text, "| Stage-1 adapter | 1")[3:] == ["+0.00 [+0.00, +0.00]", ""]
    assert _cells(text, "| (A) | 1")[3:] == ["", "+0.00 [+0.00, +0.00]"]
