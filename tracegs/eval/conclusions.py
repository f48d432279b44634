"""The paper's orderings, each marked from the paired intervals rather than by hand.

Main paper Tables 1/2 claim TRACE-GS > the baseline restorer (A) > plain 3DGS at every view count; Table 3
claims B < A < C < D (privileged teacher views) and E < F- < F (on-policy supervision, then retrieval
alignment). Each ordering is a chain of adjacent pairs; a pair *holds* when the 95% interval of the paired
difference (claimed better - claimed worse, sign flipped for lower-is-better metrics) lies entirely above
zero, is *reversed* when it lies entirely below zero, and is *not resolved* otherwise. A pair whose
variants a report does not contain is *not measured*.

A percentile bootstrap over very few scenes covers far less than 95%: with n scenes that all agree in sign,
its interval excludes zero, yet with no effect at all that happens with probability 2 * 2^-n (a sign test).
That is below the 5% a 95% interval promises only from 6 scenes on, so fewer scenes mark nothing.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from tracegs.eval.intervals import Interval

HOLDS = "holds"
REVERSED = "reversed"
NOT_RESOLVED = "not resolved"
NOT_MEASURED = "not measured"


@dataclass(frozen=True)
class Ordering:
    """A claimed order, worst first: ``("3dgs", "baseline", "tracegs")`` claims 3DGS < A < TRACE-GS."""

    chain: tuple[str, ...]

    def pairs(self) -> list[tuple[str, str]]:
        """(worse, better) for each adjacent pair of the chain."""
        return list(zip(self.chain, self.chain[1:]))


MAIN_ORDERING = Ordering(("3dgs", "baseline", "tracegs"))
GEOMETRY_ORDERING = Ordering(("B", "A", "C", "D"))
POLICY_ORDERING = Ordering(("E", "F-", "F"))
# Table 3 states each variant's difference to the frozen baseline restorer (A), the variant every claim starts from.
REFERENCE_VARIANT = "A"
# The variant standing for each method of Tables 1/2: A is the frozen baseline restorer, F the full method.
METHOD_VARIANTS = {"3dgs": "3dgs", "baseline": REFERENCE_VARIANT, "tracegs": "F"}
# Every ordering of Tables 1-3 in the variants' names (plain 3DGS keeps its own): tracegs-replicate marks them all.
TABLE3_ORDERINGS = (Ordering(tuple(METHOD_VARIANTS[m] for m in MAIN_ORDERING.chain)), GEOMETRY_ORDERING,
                    POLICY_ORDERING)
# Fig. 6 claims (better, worse): on-policy F predicts the clean frame better along its own trajectory than
# off-policy E and than the frozen baseline A.
PER_STEP_PAIRS = (("F", "E"), ("F", "A"))


MIN_SCENES = 6  # the fewest scenes whose unanimous sign is significant at 5% (2 * 2^-6 = 3.1%)


def verdict(difference: Interval | None, higher_is_better: bool = True) -> str:
    """The mark of one claimed pair from the interval of (claimed better - claimed worse)."""
    if difference is None:
        return NOT_MEASURED
    if difference.n < MIN_SCENES or math.isnan(difference.low):
        return NOT_RESOLVED
    low, high = (difference.low, difference.high) if higher_is_better else (-difference.high, -difference.low)
    if low > 0:
        return HOLDS
    if high < 0:
        return REVERSED
    return NOT_RESOLVED


# (worse, better) -> interval of better - worse, or None when either is absent from the report.
DifferenceLookup = Callable[[str, str], Interval | None]


def ordering_lines(ordering: Ordering, lookup: DifferenceLookup, labels: Mapping[str, str], context: str,
                   higher_is_better: bool = True, decimals: int = 2) -> list[str]:
    """One markdown bullet per adjacent pair, e.g. ``- TRACE-GS > Baseline (A), 3 views: **holds** (+0.31 [...])``.

    Returns no lines when no pair of the ordering was measured (the report has none of its variants).
    """
    lines = []
    for worse, better in ordering.pairs():
        difference = lookup(worse, better)
        mark = verdict(difference, higher_is_better)
        shown = f" ({difference.format(decimals, signed=True)})" if difference is not None else ""
        if difference is not None and difference.n < MIN_SCENES:
            shown = f"{shown[:-1]}; {difference.n} scene(s), fewer than the {MIN_SCENES} a verdict needs)"
        lines.append(f"- {labels.get(better, better)} > {labels.get(worse, worse)}{context}: **{mark}**{shown}")
    if all(line.endswith(f"**{NOT_MEASURED}**") for line in lines):
        return []
    return lines
