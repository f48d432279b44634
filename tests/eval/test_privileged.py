import pytest

from tracegs.eval.privileged import privileged_figures

STEP = "Stage-2 student (TRACE-GS) from R_s - Stage-1 adapter from R_s"


def _gap(rows: dict[str, list[float]]) -> dict:
    """A privileged-gap record of three scenes: row -> PSNR per scene against ground truth."""
    scenes = ["scene_a", "scene_b", "scene_c"]
    return {"rows": list(rows),
            "per_scene": {scene: {row: {"gt": values[i]} for row, values in rows.items()}
                          for i, scene in enumerate(scenes)}}


def test_the_student_is_compared_with_its_stage1_start_scene_by_scene():
    """Stage 2's own effect (the student from R_s minus the Stage-1 adapter it started from) is a paired figure of
    the report, so a Stage 2 that ends below its start is read off the same table as F - A."""
    rows = {"input R_s": [19.0, 20.0, 21.0], "baseline | R_d": [27.0, 28.0, 29.0],
            "baseline | R_s": [19.5, 20.5, 21.5], "stage1 | R_d": [26.0, 27.0, 28.0],
            "stage1 | R_s": [19.4, 20.3, 21.5], "tracegs | R_d": [26.0, 27.0, 28.0],
            "tracegs | R_s": [19.3, 20.1, 21.2]}
    figures = privileged_figures(_gap(rows))
    assert figures[STEP].mean == pytest.approx(-0.2)
    assert figures["Stage-2 student (TRACE-GS) from R_s - A from R_s"].mean == pytest.approx(-0.3)
    without_stage1 = {k: v for k, v in rows.items() if not k.startswith("stage1")}
    assert STEP not in privileged_figures(_gap(without_stage1))
