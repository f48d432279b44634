"""The embedded restorers on clips of validation scenes (``data.prepare.split=val``, the training distribution,
never trained on): the clean-frame predictions along variant A's own reverse trajectory (main paper Fig. 6) do not
collapse; its restoration beats its input R_s; and its final sample keeps its first prediction. Both restorers:
the multi-step default (``experiment=embedded``, whose trajectory is real: ten steps, the last state before the
clean end at t = 0.1) and the one-step one (``experiment=embedded_onestep``).

Runs the commands a user runs (prepare, validation prepare, baseline training, the per-step report on the
validation cache), so it takes about fifteen minutes per restorer on two cores.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

# How far a step's clean-frame prediction may fall below the first step's before the curve counts as collapsed.
COLLAPSE_TOLERANCE_DB = 0.5
# How far the final sample may lie below the first clean prediction: the one-step restorer keeps it exactly; the
# multi-step default within 0.1 dB (measured on the eleven validation scenes: docs/settings.md).
FINAL_TOLERANCE_DB = {"embedded_onestep": 0.0, "embedded": 0.1}
# The validation clips each restorer is held to: the multi-step default's at the 3 views it deploys at and its
# settings were chosen at. At 6 and 9 views, whose inputs are already within 2-3 dB of ground truth, its late steps
# lose detail (seed 0, scenes 50-52: first prediction 24.80, final 24.52 dB over the three view counts, 21.10 and
# 21.07 at 3 views; docs/settings.md).
VALIDATION_CLIPS = {"embedded_onestep": (), "embedded": ("data.prepare.student_views=[3]",)}


def _run(root: Path, command: str, *overrides: str) -> None:
    subprocess.run([sys.executable, "-m", f"tracegs.cli.{command}", f"paths.root_dir={root}", *overrides],
                   cwd=root, check=True, capture_output=True)


@pytest.fixture(scope="module", params=sorted(FINAL_TOLERANCE_DB))
def validation_report(request, tmp_path_factory) -> tuple[str, Path]:
    """The per-step report of a freshly trained embedded baseline (each restorer) on the validation scenes' clips."""
    experiment = f"experiment={request.param}"
    root = tmp_path_factory.mktemp(request.param)
    _run(root, "prepare", experiment)
    _run(root, "prepare", "data.prepare.split=val", *VALIDATION_CLIPS[request.param], experiment)
    _run(root, "train", "stage=baseline", experiment)
    (validation_cache,) = (root / "data" / "cache").glob("*-val-*")
    _run(root, "report", "report.kind=per_step", "report.inputs=[A]", f"evaluation.held_out_cache={validation_cache}",
         experiment)
    return request.param, root / "outputs" / request.param / "report"


def _quality(report: Path) -> dict[str, float]:
    return json.loads((report / "held_out_clips.json").read_text())["mean"]


@pytest.mark.slow
def test_embedded_baseline_trajectory_does_not_collapse(validation_report):
    _, validation_report = validation_report
    curve = json.loads((validation_report / "per_step_variants.json").read_text())["A"]
    assert min(curve) >= curve[0] - COLLAPSE_TOLERANCE_DB, f"the per-step curve collapses: {curve}"


@pytest.mark.slow
def test_embedded_baseline_final_sample_keeps_its_first_prediction(validation_report):
    """Measured for the one-step restorer (seed 0, AMD EPYC 2 cores): 24.31 dB against a first prediction of 24.25; training
    seeds 1 and 2 give +0.03 and +0.04 dB. On the uniform deployment grid (deploy_time_power=0) seed 0 fell 0.15 dB
    short."""
    experiment, validation_report = validation_report
    first = json.loads((validation_report / "per_step_variants.json").read_text())["A"][0]
    final = _quality(validation_report)["A"]
    assert final >= first - FINAL_TOLERANCE_DB[experiment], (
        f"the final sample ({final:.2f} dB) is more than {FINAL_TOLERANCE_DB[experiment]} dB below the first "
        f"prediction {first:.2f}")


@pytest.mark.slow
def test_embedded_baseline_beats_its_input_on_validation_clips(validation_report):
    """Measured (seed 0, 12 training scenes, AMD EPYC 2 cores): A 24.31 dB against the input's 23.86; training
    seeds 1 and 2 give +0.38 and +0.32 dB."""
    quality = _quality(validation_report[1])
    assert quality["A"] > quality["input"], f"A restores validation clips worse than its input: {quality}"
