"""The embedded default's restorer restores: on clips of validation scenes (``data.prepare.split=val``, the
training distribution, never trained on) variant A's 20-step restoration beats its input R_s, and its
clean-frame predictions along its own reverse trajectory (main paper Fig. 6) do not collapse.

Runs the commands a user runs (prepare, validation prepare, baseline training, the per-step report on the
validation cache) at the embedded default, so it takes about fifteen minutes on two cores.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

# How far a step's clean-frame prediction may fall below the first step's before the curve counts as collapsed.
COLLAPSE_TOLERANCE_DB = 0.5


def _run(root: Path, command: str, *overrides: str) -> None:
    subprocess.run([sys.executable, "-m", f"tracegs.cli.{command}", f"paths.root_dir={root}", *overrides],
                   cwd=root, check=True, capture_output=True)


@pytest.mark.slow
def test_embedded_baseline_beats_its_input_on_validation_clips(tmp_path):
    _run(tmp_path, "prepare")
    _run(tmp_path, "prepare", "data.prepare.split=val")
    _run(tmp_path, "train", "stage=baseline")
    (validation_cache,) = (tmp_path / "data" / "cache").glob("*-val-*")
    _run(tmp_path, "report", "report.kind=per_step", "report.inputs=[A]",
         f"evaluation.held_out_cache={validation_cache}")

    report = tmp_path / "outputs" / "embedded" / "report"
    quality = json.loads((report / "held_out_clips.json").read_text())["mean"]
    assert quality["A"] > quality["input"], f"A restores validation clips worse than its input: {quality}"
    curve = json.loads((report / "per_step_variants.json").read_text())["A"]
    assert min(curve) >= curve[0] - COLLAPSE_TOLERANCE_DB, f"the per-step curve collapses: {curve}"
    assert quality["A"] >= curve[0], f"the final sample ({quality['A']:.2f} dB) is worse than the first prediction"
