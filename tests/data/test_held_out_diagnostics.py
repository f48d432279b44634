"""The trajectory diagnostics on a prepared held-out cache: per scene and variant, the curves, the restorer's
output and its input, consistent with the held-out clip table."""

from __future__ import annotations

import pytest

from tracegs.eval.clips import clip_restoration_psnr
from tracegs.eval.diagnostics import VariantRoles, held_out_diagnostics
from tracegs.restorer.sampler import RestorationPipeline


def test_each_variant_gets_both_diagnostics_on_the_clips_it_restores(prepared, backbone):
    cache = prepared[0] / "cache"
    variants = {"A": VariantRoles(student=None),
                "self-taught": VariantRoles(student=None, teacher=None, teacher_views=None, distilled=True)}
    result = held_out_diagnostics(backbone, variants, cache, student_views=[3], seed=4, progress=False)
    steps = backbone.cfg.schedule.deploy_steps
    assert result["conditions"] == ["s3_it8"] and result["clips"] == 2 and result["steps"] == steps
    row = result["per_scene"]["scene_000"]
    assert row["A"]["teacher"] is None and len(row["A"]["noised"]) == steps
    assert row["A"]["noised"][0] == row["A"]["visited"][0]  # the first state is the forward-noised one
    # The same adapter on R_d = "dall" instead of R_s: the teacher sees more, the student's states are the same.
    assert len(row["self-taught"]["teacher"]) == steps and row["self-taught"]["visited"] == row["A"]["visited"]
    # The final sample and the input are the held-out clip table's, for the same clips, conditions and seeds.
    table = clip_restoration_psnr({"A": RestorationPipeline(backbone)}, cache, seed=4, progress=False)
    assert row["A"]["input"] == pytest.approx(table["mean"]["input"], abs=1e-5)
    assert row["A"]["final"] == pytest.approx(table["mean"]["A"], abs=1e-3)
    # Spread over two forked workers (one clip each, one thread as here), the same result bit for bit.
    forked = held_out_diagnostics(backbone, variants, cache, student_views=[3], seed=4, progress=False, workers=2)
    assert forked == result
    with pytest.raises(ValueError, match=r"no held-out clip at \[9\] views"):
        held_out_diagnostics(backbone, variants, cache, student_views=[9], progress=False)
    with pytest.raises(KeyError, match="no teacher condition d12 for variant C"):
        held_out_diagnostics(backbone, {"C": VariantRoles(None, None, 12, distilled=True)}, cache, [3], progress=False)
