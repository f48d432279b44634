"""Bootstrap intervals over scenes, paired differences, and the marks of the paper's orderings."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from scipy import stats

from tracegs.eval.conclusions import (
    HOLDS,
    NOT_MEASURED,
    NOT_RESOLVED,
    POLICY_ORDERING,
    REVERSED,
    ordering_lines,
    verdict,
)
from tracegs.eval.intervals import Interval, clustered, mean_interval, paired_interval, t_interval


def test_two_values_give_their_exact_percentile_interval():
    # Resamples of [0, 1] have means 0 (p=1/4), 1/2 (p=1/2), 1 (p=1/4): the 2.5% and 97.5% quantiles of the
    # bootstrap distribution are exactly 0 and 1.
    interval = mean_interval([0.0, 1.0])
    assert (interval.mean, interval.low, interval.high, interval.n) == (0.5, 0.0, 1.0, 2)


def test_large_normal_sample_matches_the_analytic_interval():
    values = np.random.default_rng(3).normal(18.0, 1.0, size=400)
    interval = mean_interval(values)
    low, high = stats.t.interval(0.95, len(values) - 1, loc=values.mean(), scale=stats.sem(values))
    assert interval.low == pytest.approx(low, abs=0.015)
    assert interval.high == pytest.approx(high, abs=0.015)
    assert interval.half_width == pytest.approx(1.96 / 20, rel=0.1)


def test_intervals_are_reproducible_and_degenerate_cases_are_plain():
    values = [17.1, 18.4, 16.9, 18.0, 17.7]
    assert mean_interval(values) == mean_interval(values)
    assert mean_interval([2.0, 2.0, 2.0]) == Interval(2.0, 2.0, 2.0, 3)
    single = mean_interval([5.0])
    assert single.mean == 5.0 and math.isnan(single.low)
    assert "n/a" in single.format()
    with pytest.raises(ValueError, match="non-empty"):
        mean_interval([])


def test_t_interval_over_seeds():
    interval = t_interval([1.0, 2.0, 3.0])
    # mean 2, sd 1, se 1/sqrt(3), t_{0.975, 2} = 4.303
    assert interval.low == pytest.approx(2 - 4.3027 / math.sqrt(3), abs=1e-3)
    assert interval.high == pytest.approx(2 + 4.3027 / math.sqrt(3), abs=1e-3)


def _scores(offsets: dict[str, float], shift: float) -> dict[tuple[str, str], float]:
    """(scene, views) -> a value dominated by the scene's content, plus ``shift`` (the method's effect)."""
    return {(scene, views): 15.0 + offset + 0.1 * int(views) + shift
            for scene, offset in offsets.items() for views in ("3", "6", "9")}


def test_paired_difference_is_paired_by_scene_and_view_count():
    rng = random.Random(0)
    offsets = {f"scene_{i}": rng.uniform(-4, 4) for i in range(8)}
    a, b = _scores(offsets, 0.3), _scores(offsets, 0.0)
    # Same keys listed in another order: pairing goes by key, so the difference is exactly +0.3 everywhere.
    shuffled_b = dict(rng.sample(list(b.items()), len(b)))
    paired = paired_interval(a, shuffled_b, cluster=lambda key: key[0])
    assert paired.mean == pytest.approx(0.3)
    assert paired.low == pytest.approx(0.3) and paired.high == pytest.approx(0.3)
    assert verdict(paired) == HOLDS
    # Pairing the wrong scenes (values shuffled among keys) destroys the effect: a wide interval.
    wrong = dict(zip(b, rng.sample(list(b.values()), len(b))))
    unpaired = paired_interval(a, wrong, cluster=lambda key: key[0])
    assert unpaired.half_width > 1.0
    assert verdict(unpaired) == NOT_RESOLVED


def test_paired_difference_refuses_different_units():
    a = {("s0", "3"): 1.0, ("s1", "3"): 2.0}
    with pytest.raises(ValueError, match="only in the first"):
        paired_interval(a, {("s0", "3"): 1.0, ("s1", "6"): 2.0})


def test_clusters_average_the_view_counts_of_a_scene():
    values = {("a", "3"): 1.0, ("a", "6"): 3.0, ("b", "3"): 10.0, ("b", "6"): 20.0}
    assert clustered(values, lambda key: key[0]) == [2.0, 15.0]


@pytest.mark.parametrize(("low", "high", "higher_is_better", "expected"), [
    (0.1, 0.5, True, HOLDS),
    (-0.5, -0.1, True, REVERSED),
    (-0.1, 0.5, True, NOT_RESOLVED),
    (0.0, 0.5, True, NOT_RESOLVED),  # touching zero is not resolved
    (-0.05, -0.01, False, HOLDS),  # LPIPS: the claimed-better method has the lower value
    (0.01, 0.05, False, REVERSED),
])
def test_verdict_marks(low, high, higher_is_better, expected):
    assert verdict(Interval((low + high) / 2, low, high, 8), higher_is_better) == expected


def test_verdict_of_missing_or_single_values():
    assert verdict(None) == NOT_MEASURED
    assert verdict(Interval(0.3, math.nan, math.nan, 1)) == NOT_RESOLVED


def test_too_few_scenes_mark_nothing():
    # Two scenes that agree give a bootstrap interval above zero, which a coin does one time in four.
    two = paired_interval({"a": 1.0, "b": 2.0}, {"a": 0.5, "b": 1.0})
    assert two.low > 0
    assert verdict(two) == NOT_RESOLVED
    lines = ordering_lines(POLICY_ORDERING, lambda worse, better: two, {}, "")
    assert lines[0] == "- F- > E: **not resolved** (+0.75 [+0.50, +1.00]; 2 scene(s), fewer than the 6 a verdict needs)"
    six = paired_interval({str(i): 1.0 + i for i in range(6)}, {str(i): 0.5 + i for i in range(6)})
    assert verdict(six) == HOLDS


def test_ordering_lines_mark_each_pair_and_omit_unmeasured_orderings():
    intervals = {("E", "F-"): Interval(0.2, 0.1, 0.3, 8), ("F-", "F"): Interval(-0.2, -0.3, -0.1, 8)}
    lines = ordering_lines(POLICY_ORDERING, lambda worse, better: intervals.get((worse, better)), {}, ", PSNR")
    assert lines == ["- F- > E, PSNR: **holds** (+0.20 [+0.10, +0.30])",
                     "- F > F-, PSNR: **reversed** (-0.20 [-0.30, -0.10])"]
    partly = ordering_lines(POLICY_ORDERING, lambda worse, better: intervals.get((worse, better))
                            if worse == "E" else None, {}, "")
    assert partly[1] == "- F > F-: **not measured**"
    assert ordering_lines(POLICY_ORDERING, lambda worse, better: None, {}, "") == []
