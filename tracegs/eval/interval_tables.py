"""The report's tables with their uncertainty: per-scene values as CSV, means with 95% intervals over test
scenes, the paired differences the paper's claims are about, and the claims marked from those intervals.

Per-scene values come from the evaluation's ``per_scene.json`` (``{scene: {method: {views: {metric: v}}}}``,
written by ``eval.merge.merge_results``); each value is already the mean over the scene's test views,
so the interval is over scenes (``tracegs.eval.intervals``). The point estimates equal the plain tables'.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path

from tracegs.eval.conclusions import (
    GEOMETRY_ORDERING,
    MAIN_ORDERING,
    POLICY_ORDERING,
    REFERENCE_VARIANT,
    ordering_lines,
)
from tracegs.eval.intervals import Interval, clustered, mean_interval, paired_interval
from tracegs.eval.labels import HIGHER_IS_BETTER, METHOD_LABELS, METRIC_DECIMALS, METRIC_LABELS
from tracegs.eval.metrics import HEADLINE_METRICS, METRIC_NAMES
from tracegs.io import atomic_write

# The paired differences of Tables 1/2: (minuend, subtrahend).
MAIN_DIFFERENCES = (("tracegs", "baseline"), ("baseline", "3dgs"))

INPUT = "input"  # the held-out clip table's row of the unrestored R_s (tracegs.eval.clips.INPUT)
UnitScores = dict[tuple[str, str], float]  # (scene, views) -> a method's scene mean at that view count


def _scene(key: tuple[str, str]) -> str:
    return key[0]


def unit_scores(per_scene: Mapping, method: str, metric: str, views: Sequence[str] | None = None) -> UnitScores | None:
    """``{(scene, views): value}`` of one method and metric; None when any scene lacks it (e.g. LPIPS n/a)."""
    scores: UnitScores = {}
    for scene, methods in per_scene.items():
        for k, row in methods.get(method, {}).items():
            if views is None or k in views:
                scores[(scene, k)] = row.get(metric)
    if not scores or any(v is None for v in scores.values()):
        return None
    return scores


def measured_metrics(per_scene: Mapping, methods: Sequence[str]) -> list[str]:
    """The metrics every method has a value for on every scene (LPIPS drops out without its weights)."""
    return [m for m in METRIC_NAMES if all(unit_scores(per_scene, method, m) is not None for method in methods)]


def methods_of(per_scene: Mapping) -> list[str]:
    present = {m for methods in per_scene.values() for m in methods}
    return [m for m in METHOD_LABELS if m in present] + sorted(present - set(METHOD_LABELS))


def _label(method: str) -> str:
    return METHOD_LABELS.get(method, method)


def difference_label(a: str, b: str) -> str:
    """``TRACE-GS − A``: how a paired difference is named in every table."""
    short = {"baseline": REFERENCE_VARIANT, INPUT: "input R_s"}
    return f"{short.get(a, _label(a))} − {short.get(b, _label(b))}"


# ------------------------------------------------------------------------------------ Tables 1/2


def main_difference(per_scene: Mapping, better: str, worse: str, metric: str, views: str) -> Interval | None:
    """``better - worse`` at one view count, paired by scene (None when a method is absent)."""
    a = unit_scores(per_scene, better, metric, [views])
    b = unit_scores(per_scene, worse, metric, [views])
    return None if a is None or b is None else paired_interval(a, b)


def main_intervals_markdown(per_scene: Mapping, views: Sequence[str], conclusions: bool = True) -> str:
    """Tables 1/2 with 95% intervals over scenes, the paired differences, and (``conclusions``) the claims marked."""
    methods = methods_of(per_scene)
    metrics = measured_metrics(per_scene, methods)
    scenes = sorted(per_scene)
    header = ["Method"] + [f"{METRIC_LABELS[m]} {v}" for m in metrics for v in views]
    lines = [f"Mean over {len(scenes)} test scene(s) with a 95% bootstrap interval over scenes:", "",
             "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for method in methods:
        cells = [_label(method)]
        for metric in metrics:
            for v in views:
                cells.append(mean_interval(list(unit_scores(per_scene, method, metric, [v]).values()))
                             .format(METRIC_DECIMALS[metric]))
        lines.append("| " + " | ".join(cells) + " |")
    pairs = [(a, b) for a, b in MAIN_DIFFERENCES if a in methods and b in methods]
    if pairs:
        lines += ["", "Paired differences (the same scenes at the same view count), 95% bootstrap interval:", "",
                  "| " + " | ".join(["Difference", *header[1:]]) + " |", "|" + "---|" * len(header)]
        for a, b in pairs:
            cells = [difference_label(a, b)]
            cells += [main_difference(per_scene, a, b, m, v).format(METRIC_DECIMALS[m], signed=True)
                      for m in metrics for v in views]
            lines.append("| " + " | ".join(cells) + " |")
    marked = main_conclusions(per_scene, views, metrics) if conclusions else []
    if marked:
        lines += ["", "The paper's ordering (holds / reversed / not resolved by the 95% paired interval):", "",
                  *marked]
    return "\n".join(lines) + "\n"


def main_conclusions(per_scene: Mapping, views: Sequence[str], metrics: Sequence[str]) -> list[str]:
    lines = []
    for metric in metrics:
        for v in views:
            lines += ordering_lines(
                MAIN_ORDERING, lambda worse, better, m=metric, k=v: main_difference(per_scene, better, worse, m, k),
                METHOD_LABELS, f", {v} views, {METRIC_LABELS[metric][:-1]}", HIGHER_IS_BETTER[metric],
                METRIC_DECIMALS[metric])
    return lines


def write_per_scene_csv(per_scene: Mapping, path: str | Path, column: str = "method") -> Path:
    """One row per (scene, view count, method or ``column``): each metric's mean over the scene's test views."""
    path = Path(path)
    with atomic_write(path) as tmp, tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["scene", "views", column, *METRIC_NAMES])
        for scene in sorted(per_scene):
            for method, by_views in per_scene[scene].items():
                for v, row in by_views.items():
                    writer.writerow([scene, v, method, *["" if row.get(m) is None else repr(float(row[m]))
                                                          for m in METRIC_NAMES]])
    return path


def write_main_intervals(per_scene: Mapping, out_dir: str | Path, views: Sequence[str]) -> Path:
    """``per_scene.csv`` and ``intervals.md`` beside an evaluation's ``results.json``; returns the markdown."""
    out_dir = Path(out_dir)
    write_per_scene_csv(per_scene, out_dir / "per_scene.csv")
    path = out_dir / "intervals.md"
    with atomic_write(path) as tmp:
        tmp.write_text(main_intervals_markdown(per_scene, views))
    return path


# ----------------------------------------------------------------------------------------- Table 3


def ablation_intervals_markdown(variants: Mapping[str, tuple[Mapping, str]]) -> str:
    """Table 3 with intervals: ``variants[name] = (per_scene, method)``. Each variant is averaged over the view
    counts evaluated; intervals and the differences to A resample whole scenes (paired by scene and views)."""
    names = list(variants)
    metrics = [m for m in HEADLINE_METRICS
               if all(unit_scores(per_scene, method, m) is not None for per_scene, method in variants.values())]
    scores = {(name, m): unit_scores(*variants[name], m) for name in names for m in metrics}

    def difference(better: str, worse: str, metric: str) -> Interval | None:
        if better not in variants or worse not in variants:
            return None
        return paired_interval(scores[(better, metric)], scores[(worse, metric)], cluster=_scene)

    lines = ["Mean over test scenes and view counts with a 95% bootstrap interval over scenes, and the paired "
             "difference to A (same scenes, same view counts):", "",
             "| Variant | " + " | ".join(f"{METRIC_LABELS[m]} | − A" for m in metrics) + " |",
             "|---|" + "---|---|" * len(metrics)]
    for name in names:
        cells = [name]
        for m in metrics:
            cells.append(mean_interval(clustered(scores[(name, m)], _scene)).format(METRIC_DECIMALS[m]))
            to_a = difference(name, REFERENCE_VARIANT, m) if name != REFERENCE_VARIANT else None
            cells.append(to_a.format(METRIC_DECIMALS[m], signed=True) if to_a else "")
        lines.append("| " + " | ".join(cells) + " |")
    conclusions = []
    for ordering in (GEOMETRY_ORDERING, POLICY_ORDERING):
        for m in metrics:
            conclusions += ordering_lines(ordering, lambda worse, better, m=m: difference(better, worse, m), {},
                                          f", {METRIC_LABELS[m][:-1]}", HIGHER_IS_BETTER[m], METRIC_DECIMALS[m])
    if conclusions:
        lines += ["", "The paper's orderings (holds / reversed / not resolved by the 95% paired interval):", "",
                  *conclusions]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------ Fig. 6


def per_step_intervals(
        unit_curves: Mapping[tuple[str, str], Mapping[str, Sequence[float]]]) -> dict[str, list[Interval]]:
    """Per label and reverse step: the mean clean-frame PSNR with its interval over scenes. ``unit_curves`` maps
    (scene, views) to each label's curve; the view counts of a scene are averaged first (Fig. 6 averages
    across view settings)."""
    labels = list(next(iter(unit_curves.values())))
    bands = {}
    for label in labels:
        steps = len(next(iter(unit_curves.values()))[label])
        bands[label] = [mean_interval(clustered({key: curves[label][i] for key, curves in unit_curves.items()},
                                                _scene))
                        for i in range(steps)]
    return bands


def per_step_intervals_markdown(unit_curves: Mapping[tuple[str, str], Mapping[str, Sequence[float]]],
                                pairs: Sequence[tuple[str, str]] = ()) -> str:
    """Fig. 6 as a table: per reverse step, each curve's mean with its interval over scenes, and the paired
    differences ``pairs`` (e.g. F - E) within each (scene, views) first."""
    bands = per_step_intervals(unit_curves)
    labels = list(bands)
    pairs = [(a, b) for a, b in pairs if a in bands and b in bands]
    header = ["step", *(_label(label) for label in labels), *(difference_label(a, b) for a, b in pairs)]
    lines = ["Clean-frame PSNR (dB) at each reverse step, 95% bootstrap interval over scenes:", "",
             "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for step in range(len(bands[labels[0]])):
        cells = [str(step + 1), *(bands[label][step].format() for label in labels)]
        for a, b in pairs:
            at_step = {key: {label: curves[label][step] for label in (a, b)} for key, curves in unit_curves.items()}
            cells.append(paired_interval({k: v[a] for k, v in at_step.items()}, {k: v[b] for k, v in at_step.items()},
                                         cluster=_scene).format(signed=True))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_per_step_intervals(unit_curves: Mapping[tuple[str, str], Mapping[str, Sequence[float]]],
                             out_dir: str | Path, stem: str,
                             pairs: Sequence[tuple[str, str]] = ()) -> dict[str, tuple[list[float], list[float]]]:
    """``<stem>_per_scene.csv`` (scene, views, label, step, psnr) and ``<stem>_intervals.md``; returns each
    label's (low, high) band for the Fig. 6 plot."""
    out_dir = Path(out_dir)
    with atomic_write(out_dir / f"{stem}_per_scene.csv") as tmp, tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["scene", "views", "label", "step", "psnr"])
        for (scene, views), curves in sorted(unit_curves.items()):
            for label, curve in curves.items():
                writer.writerows([scene, views, label, step, repr(float(v))] for step, v in enumerate(curve, 1))
    with atomic_write(out_dir / f"{stem}_intervals.md") as tmp:
        tmp.write_text(per_step_intervals_markdown(unit_curves, pairs))
    return {label: ([i.low for i in band], [i.high for i in band])
            for label, band in per_step_intervals(unit_curves).items()}


# ------------------------------------------------------------------------------------ held-out clips


def held_out_intervals_markdown(quality: Mapping) -> str:
    """The held-out clip table (``tracegs.eval.clips``) with 95% intervals over scenes, and each restorer's
    paired gain over its input R_s and TRACE-GS - A, paired by scene and student condition (K views, snapshot)."""
    per_scene = quality["per_scene"]
    labels, conditions = list(quality["mean"]), list(quality["conditions"])

    def scores(label: str, condition: str | None) -> dict[tuple[str, str], float]:
        return {(scene, cond): rows[cond][label] for scene, rows in per_scene.items() for cond in rows
                if condition is None or cond == condition}

    def interval(label: str, condition: str | None) -> Interval:
        return mean_interval(clustered(scores(label, condition), _scene))

    def names(label: str) -> str:
        return "input R_s" if label == INPUT else _label(label)

    columns = [*conditions, None]
    header = ["", *conditions, "mean"]
    lines = ["PSNR (dB) with a 95% bootstrap interval over the held-out scenes:", "",
             "| " + " | ".join(["R_s condition", *(names(label) for label in labels)]) + " |",
             "|" + "---|" * (len(labels) + 1)]
    for condition in columns:
        lines.append("| " + " | ".join([condition or "mean", *(interval(label, condition).format()
                                                               for label in labels)]) + " |")
    restorers = [label for label in labels if label != INPUT]
    pairs = [(label, INPUT) for label in restorers]
    if "tracegs" in restorers and "baseline" in restorers:
        pairs.append(("tracegs", "baseline"))
    lines += ["", "Paired differences (same scenes, same condition), 95% bootstrap interval:", "",
              "| " + " | ".join(["difference", *header[1:]]) + " |", "|" + "---|" * len(header)]
    for a, b in pairs:
        cells = [difference_label(a, b)]
        cells += [paired_interval(scores(a, c), scores(b, c), cluster=_scene).format(signed=True) for c in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
