"""The privileged gap on held-out clips: each restorer from R_d and from R_s, against GT and against R_d."""

from __future__ import annotations

import pytest

from tracegs.eval.clips import clip_restoration_psnr
from tracegs.eval.privileged import privileged_gap, privileged_gap_markdown
from tracegs.restorer.sampler import RestorationPipeline


def test_gap_rows_match_the_clip_scores_and_the_table_reads_them(prepared, backbone):
    cache = prepared[0] / "cache"
    pipeline = RestorationPipeline(backbone)
    gap = privileged_gap({"baseline": pipeline}, cache, teacher_views=None, progress=False)
    assert gap["teacher"] == "dall" and gap["clips"] == 2
    assert gap["rows"] == ["input R_d", "input R_s", "baseline | R_d", "baseline | R_s"]
    scene = gap["per_scene"]["scene_000"]
    assert set(scene["input R_d"]) == {"gt"}  # R_d against itself measures nothing
    assert set(scene["baseline | R_s"]) == {"gt", "R_d"}
    # The input R_s row is the held-out clip table's input row (the same clips and conditions).
    clips = clip_restoration_psnr({"baseline": pipeline}, cache, progress=False)
    assert scene["input R_s"]["gt"] == pytest.approx(clips["mean"]["input"], abs=1e-6)
    table = privileged_gap_markdown(gap)
    assert "| Baseline (A) from R_d |" in table
    assert "| input (no restoration) | " in table
    assert "[n/a, 1 value]" in table  # one scene: no interval, said so
    assert gap["conditions"] == ["s3_it8"]
    with pytest.raises(ValueError, match=r"no student condition at \[9\] views"):
        privileged_gap({"baseline": pipeline}, cache, student_views=[9], progress=False)
    assert "| input R_d | " in table and " | — |" in table
