"""95% confidence intervals over test scenes, and paired differences between methods.

The paper's protocol averages each metric over a scene's test views, then over scenes (supplement B), so the
scene is the unit of replication: an interval says how much the mean over scenes would move with another
draw of scenes. Intervals are percentile bootstraps from ``scipy.stats.bootstrap`` with a fixed generator
seed, so a report is reproducible to the last digit. The percentile method is used rather than BCa because
BCa's jackknife acceleration is undefined for the 2-8 scenes of the embedded benchmark; with 2 scenes the
percentile interval is simply [lower scene, upper scene], which is what a report should show.

A claim such as "TRACE-GS > A" is about a paired difference: both methods are scored on the same scenes at
the same view counts, so the difference is taken within each (scene, view count) first and only then
resampled. Pairing removes the scene-to-scene spread both methods share, which dominates the unpaired
intervals. Differences averaged over view counts (Table 3) resample whole scenes, the views of one scene
staying together, since they share the scene's content.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

CONFIDENCE = 0.95
RESAMPLES = 9999
RANDOM_SEED = 0  # fixed: the same per-scene values always give the same interval


@dataclass(frozen=True)
class Interval:
    """A mean with its confidence interval; ``low``/``high`` are NaN when one value cannot give a spread."""

    mean: float
    low: float
    high: float
    n: int

    @property
    def half_width(self) -> float:
        return (self.high - self.low) / 2

    def format(self, decimals: int = 2, signed: bool = False) -> str:
        """``18.23 [17.91, 18.55]`` (``+0.12 [-0.05, +0.30]`` when ``signed``)."""
        spec = f"{'+' if signed else ''}.{decimals}f"
        if math.isnan(self.low):
            return f"{self.mean:{spec}} [n/a, {self.n} value]"
        return f"{self.mean:{spec}} [{self.low:{spec}}, {self.high:{spec}}]"


def mean_interval(values: Sequence[float], confidence: float = CONFIDENCE) -> Interval:
    """The mean of ``values`` (one per scene) and its percentile-bootstrap interval."""
    data = np.asarray(values, dtype=np.float64)
    if data.ndim != 1 or data.size == 0:
        raise ValueError(f"need a non-empty list of per-scene values, got shape {data.shape}")
    if np.isnan(data).any():
        raise ValueError("per-scene values contain NaN")
    mean = float(data.mean())
    if data.size == 1:
        return Interval(mean, math.nan, math.nan, 1)
    if np.ptp(data) == 0:  # every resample has the same mean; scipy would warn about degenerate data
        return Interval(mean, mean, mean, int(data.size))
    result = stats.bootstrap((data,), np.mean, confidence_level=confidence, n_resamples=RESAMPLES,
                             method="percentile", rng=np.random.default_rng(RANDOM_SEED))
    return Interval(mean, float(result.confidence_interval.low), float(result.confidence_interval.high),
                    int(data.size))


def clustered(values: Mapping[Hashable, float], cluster: Callable[[Hashable], Hashable]) -> list[float]:
    """Average the values of each cluster (e.g. the view counts of one scene), in first-seen order."""
    groups: dict[Hashable, list[float]] = defaultdict(list)
    for key, value in values.items():
        groups[cluster(key)].append(value)
    return [float(np.mean(group)) for group in groups.values()]


def paired_differences(a: Mapping[Hashable, float], b: Mapping[Hashable, float]) -> dict[Hashable, float]:
    """``a[key] - b[key]`` for every key (scene, view count, ...); both must cover the same keys."""
    if set(a) != set(b):
        only_a, only_b = sorted(map(str, set(a) - set(b))), sorted(map(str, set(b) - set(a)))
        raise ValueError(f"paired difference over different units: only in the first {only_a}, "
                         f"only in the second {only_b}")
    return {key: a[key] - b[key] for key in a}


def paired_interval(a: Mapping[Hashable, float], b: Mapping[Hashable, float],
                    cluster: Callable[[Hashable], Hashable] | None = None) -> Interval:
    """Mean of ``a - b`` paired by key, with its bootstrap interval over clusters of keys (default: each key
    its own cluster; ``cluster=lambda key: key[0]`` resamples whole scenes of (scene, views) keys)."""
    differences = paired_differences(a, b)
    return mean_interval(clustered(differences, cluster) if cluster else list(differences.values()))


def t_interval(values: Sequence[float], confidence: float = CONFIDENCE) -> Interval:
    """Student-t interval of the mean, for the spread over a handful of training seeds (too few to bootstrap)."""
    data = np.asarray(values, dtype=np.float64)
    mean = float(data.mean())
    if data.size < 2:
        return Interval(mean, math.nan, math.nan, int(data.size))
    low, high = stats.t.interval(confidence, data.size - 1, loc=mean, scale=stats.sem(data)) \
        if np.ptp(data) > 0 else (mean, mean)
    return Interval(mean, float(low), float(high), int(data.size))
