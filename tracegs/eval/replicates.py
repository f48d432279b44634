"""tracegs-replicate's report: Table 3's variants, each trained for several training seeds, on the same test scenes.

Per seed, each variant's evaluation folder holds ``per_scene.json`` (deployment; plain 3DGS is evaluated once, in
its own folder, and shared by every seed), and the seed's diagnostics folder ``diagnostics.json`` (held-out clips:
per-step curves, exposure gap, teacher advantage, final sample and input; tracegs.eval.diagnostics). Per scene,
the seeds are averaged first; the 95% intervals are then over scenes (``tracegs.eval.intervals``), so the
seed-to-seed noise of each scene enters them, and the spread over seeds of each figure is reported next to them.
"""

from __future__ import annotations

import json
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tracegs.eval.conclusions import (
    METHOD_VARIANTS,
    MIN_SCENES,
    PER_STEP_PAIRS,
    REFERENCE_VARIANT,
    TABLE3_ORDERINGS,
    verdict,
)
from tracegs.eval.interval_tables import (
    measured_metrics,
    per_step_intervals,
    unit_scores,
    write_per_scene_csv,
    write_per_step_intervals,
)
from tracegs.eval.intervals import Interval, mean_interval, paired_interval, t_interval
from tracegs.eval.labels import HIGHER_IS_BETTER, METRIC_DECIMALS, METRIC_LABELS, RESTORER_LABELS, STAGE1
from tracegs.eval.privileged import privileged_figures, privileged_gap_markdown
from tracegs.eval.tables_and_figures import plot_per_step_quality
from tracegs.io import atomic_write

# The instrument's target: the 95% interval of F - A at 3 views no wider than +-0.2 dB PSNR.
TARGET_HALF_WIDTH_DB = 0.2
PLAIN = "3dgs"  # plain 3DGS, the row under every variant
# The frozen baseline restorer and the full method (Table 3's first and last rows).
REFERENCE, TRACEGS = REFERENCE_VARIANT, METHOD_VARIANTS["tracegs"]


def label(name: str) -> str:
    """A variant as the paper names it: its name in parentheses, a trailing ``-`` written ``⁻``; plain 3DGS as
    ``3DGS``, the diagnostics' Stage-1 row by its restorer label."""
    if name == PLAIN:
        return "3DGS"
    return RESTORER_LABELS[STAGE1] if name == STAGE1 else f"({name.replace('-', '⁻')})"


@dataclass
class ReplicateInputs:
    """Where one tracegs-replicate run's results are: ``eval_dirs[seed] / <variant> / per_scene.json`` (scored under
    ``methods[variant]``), ``three_dgs_dir / per_scene.json`` and ``diagnostics_dirs[seed] / diagnostics.json``;
    ``variants`` in Table 3's row order, each described as its config does."""

    seeds: list[int]
    variants: list[str]
    descriptions: dict[str, str]
    methods: dict[str, str]
    eval_dirs: dict[int, Path]
    three_dgs_dir: Path
    diagnostics_dirs: dict[int, Path]
    # ``privileged_dirs[seed] / privileged_gap.json`` (tracegs-report report.kind=privileged): A and the student
    # restoring the held-out clips from R_d and from R_s; none: no privileged-gap figures.
    privileged_dirs: dict[int, Path] = field(default_factory=dict)


def mean_tree(trees: Sequence[Any]) -> Any:
    """Average nested dicts / lists of numbers leaf by leaf (keys present in every tree; a None leaf stays
    None; strings and other leaves are taken from the first tree)."""
    first = trees[0]
    if isinstance(first, Mapping):
        return {key: mean_tree([t[key] for t in trees]) for key in first if all(key in t for t in trees)}
    if isinstance(first, list) and first and all(isinstance(v, (int, float)) for v in first):
        return [statistics.fmean(values) for values in zip(*trees)]
    if isinstance(first, (int, float)) and not isinstance(first, bool):
        if any(t is None for t in trees):
            return None
        return first if all(t == first for t in trees) else statistics.fmean(trees)  # counts stay integers
    return first


def _read(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"replicate report: {path} is missing (did that seed's step finish?)")
    return json.loads(path.read_text())


def seed_tables(inputs: ReplicateInputs) -> list[dict]:
    """Per seed, ``{scene: {variant or "3dgs": {views: {metric: value}}}}``: each variant's deployment under the
    method standing for it, and the shared plain 3DGS."""
    plain = _read(inputs.three_dgs_dir / "per_scene.json")
    tables = []
    for seed in inputs.seeds:
        table: dict[str, dict] = {scene: {PLAIN: methods[PLAIN]} for scene, methods in plain.items()}
        for variant in inputs.variants:
            for scene, methods in _read(inputs.eval_dirs[seed] / variant / "per_scene.json").items():
                table[scene][variant] = methods[inputs.methods[variant]]
        tables.append(table)
    return tables


def _cell(interval: Interval | None, decimals: int, signed: bool = False) -> str:
    return "" if interval is None else interval.format(decimals, signed=signed)


def difference(per_scene: Mapping, better: str, worse: str, metric: str, views: str) -> Interval | None:
    """``better - worse`` at one view count, paired by scene (None when either is not in the run)."""
    a, b = unit_scores(per_scene, better, metric, [views]), unit_scores(per_scene, worse, metric, [views])
    return None if a is None or b is None else paired_interval(a, b)


def _seed_means(per_seed: Sequence[Mapping], better: str, worse: str | None, metric: str, views: str) -> list[float]:
    """Per seed: the mean over scenes of ``better`` (minus ``worse``)."""
    values = []
    for table in per_seed:
        a = unit_scores(table, better, metric, [views])
        b = unit_scores(table, worse, metric, [views]) if worse else None
        values.append(statistics.fmean(a[k] - (b[k] if b else 0.0) for k in a))
    return values


def table3_markdown(per_seed: Sequence[Mapping], seeds: Sequence[int], averaged: Mapping, rows: Sequence[str],
                    views: Sequence[str], metrics: Sequence[str]) -> str:
    """Each variant's mean [95% over scenes], its mean per training seed and their spread, and its paired
    difference to A, per view count and metric."""
    lines = []
    for metric in metrics:
        decimals = METRIC_DECIMALS[metric]
        for v in views:
            lines += [f"{METRIC_LABELS[metric]} at {v} views:", "",
                      "| variant | mean [95% CI over scenes] | " + " / ".join(f"seed {seed}" for seed in seeds)
                      + f" | sd over seeds | − {label(REFERENCE)} [95% CI] |", "|---|---|---|---|---|"]
            for name in rows:
                means = _seed_means(per_seed, name, None, metric, v)
                overall = mean_interval(list(unit_scores(averaged, name, metric, [v]).values()))
                to_a = difference(averaged, name, REFERENCE, metric, v) if name != REFERENCE else None
                spread = f"{statistics.stdev(means):.{decimals}f}" if len(means) > 1 else "n/a"
                per_seed_cell = " / ".join(f"{m:.{decimals}f}" for m in means)
                lines.append(f"| {label(name)} | {overall.format(decimals)} | {per_seed_cell} | {spread} | "
                             f"{_cell(to_a, decimals, signed=True)} |")
            lines.append("")
    return "\n".join(lines)


def orderings_markdown(per_seed: Sequence[Mapping], averaged: Mapping, present: set[str], views: Sequence[str],
                       metrics: Sequence[str]) -> tuple[str, dict[str, str]]:
    """Every adjacent pair of the paper's orderings (conclusions.TABLE3_ORDERINGS) marked from the 95% interval of
    its paired difference over scenes (seeds averaged per scene first), with the difference per training seed
    and its t-interval over seeds beside it. Returns the table and ``{"(B) < (A), PSNR, 3 views": verdict}``."""
    lines = ["| claim | metric | views | better − worse [95% CI over scenes] | verdict | per seed | "
             "95% t-interval over seeds |", "|---|---|---|---|---|---|---|"]
    verdicts = {}
    for ordering in TABLE3_ORDERINGS:
        for worse, better in ordering.pairs():
            for metric in metrics:
                for v in views:
                    claim = f"{label(worse)} < {label(better)}"
                    if not {worse, better} <= present:
                        mark, shown, seeds, over_seeds = verdict(None), "", "", ""
                    else:
                        signed = 1 if HIGHER_IS_BETTER[metric] else -1
                        interval = difference(averaged, better, worse, metric, v)
                        mark = verdict(interval, HIGHER_IS_BETTER[metric])
                        shown = interval.format(METRIC_DECIMALS[metric], signed=True)
                        per = [signed * d for d in _seed_means(per_seed, better, worse, metric, v)]
                        seeds = " / ".join(f"{d:+.{METRIC_DECIMALS[metric]}f}" for d in per)
                        over_seeds = t_interval(per).format(METRIC_DECIMALS[metric], signed=True)
                    verdicts[f"{claim}, {METRIC_LABELS[metric][:-1]}, {v} views"] = mark
                    lines.append(f"| {claim} | {METRIC_LABELS[metric]} | {v} | {shown} | **{mark}** | {seeds} | "
                                 f"{over_seeds} |")
    return "\n".join(lines) + "\n", verdicts


def instrument(averaged: Mapping, views: str) -> tuple[str, Interval | None]:
    """The target: is the 95% interval of F - A at ``views`` views within +-0.2 dB?"""
    gap = difference(averaged, TRACEGS, REFERENCE, "psnr", views)
    if gap is None:
        return f"Instrument: {label(TRACEGS)} − {label(REFERENCE)} at {views} views was not measured.", None
    if gap.n < MIN_SCENES:
        met = f"not assessable from {gap.n} scenes, fewer than {MIN_SCENES}"
    else:
        met = "met" if gap.half_width <= TARGET_HALF_WIDTH_DB else "not met"
    return (f"Instrument: the 95% interval of {label(TRACEGS)} − {label(REFERENCE)} at {views} views is "
            f"{gap.format(signed=True)} dB, half-width ±{gap.half_width:.2f} dB "
            f"(target ≤ ±{TARGET_HALF_WIDTH_DB} dB: {met}).", gap)


# ------------------------------------------------------------------------------------ held-out diagnostics


def _scene_values(diagnostics: Mapping, variant: str, field: str) -> dict[str, Any]:
    return {scene: rows[variant][field] for scene, rows in diagnostics["per_scene"].items()}


def held_out_markdown(diagnostics: Mapping, variants: Sequence[str], start: str | None = None) -> str:
    """Each variant's final sample on the held-out clips, against its input R_s, against the reference and (with
    ``start``, the row of the Stage-1 adapter) against the adapter the students start from."""
    references = [REFERENCE] + ([start] if start is not None else [])
    lines = ["| variant | restored [95% CI over scenes] | − input R_s | "
             + " | ".join(f"− {label(r)}" for r in references) + " |", "|---|---|---|" + "---|" * len(references)]
    inputs = {scene: rows[variants[0]]["input"] for scene, rows in diagnostics["per_scene"].items()}
    lines.append(f"| input R_s | {mean_interval(list(inputs.values())).format()} | |" + " |" * len(references))
    for name in variants:
        final = _scene_values(diagnostics, name, "final")
        against = [paired_interval(final, _scene_values(diagnostics, r, "final")).format(signed=True)
                   if name != r and r in variants else "" for r in references]
        lines.append(f"| {label(name)} | {mean_interval(list(final.values())).format()} | "
                     f"{paired_interval(final, inputs).format(signed=True)} | {' | '.join(against)} |")
    return "\n".join(lines) + "\n"


def _per_step(diagnostics: Mapping, variant: str, a: str, b: str) -> dict[str, list[float]] | None:
    """Per scene, ``a - b`` at each step (``b`` None: ``a`` itself); None when the variant has no ``a`` curve."""
    first = next(iter(diagnostics["per_scene"].values()))[variant]
    if first[a] is None:
        return None
    return {scene: [x - y for x, y in zip(rows[variant][a], rows[variant][b])]
            for scene, rows in diagnostics["per_scene"].items()}


def late_half(curve: Sequence[float]) -> float:
    """The mean of a per-step curve over the later half of the reverse trajectory (steps M/2 + 1 .. M), where
    the paper places exposure bias ("the variants remain close in early steps but separate in the later half")."""
    return statistics.fmean(curve[len(curve) // 2:])


def per_step_table(diagnostics: Mapping, variants: Sequence[str], a: str, b: str
                   ) -> tuple[str, dict[str, list], dict[str, Interval]]:
    """Per reverse step (rows) and variant (columns): the mean of ``a - b`` [95% CI over scenes], then each
    variant's mean over the steps after the first and over the later half (per scene first). Returns the table,
    per variant its per-step intervals, and per variant the interval of its later-half mean."""
    curves = {name: c for name in variants if (c := _per_step(diagnostics, name, a, b)) is not None}
    if not curves:
        return "", {}, {}
    steps = len(next(iter(next(iter(curves.values())).values())))
    bands = {name: [mean_interval([curve[i] for curve in by_scene.values()]) for i in range(steps)]
             for name, by_scene in curves.items()}
    late = {n: mean_interval([late_half(curve) for curve in by_scene.values()]) for n, by_scene in curves.items()}
    lines = ["| step | " + " | ".join(label(n) for n in curves) + " |", "|---|" + "---|" * len(curves)]
    for i in range(steps):
        lines.append(f"| {i + 1} | " + " | ".join(bands[n][i].format(signed=True) for n in curves) + " |")
    if steps > 1:
        later = {n: mean_interval([statistics.fmean(curve[1:]) for curve in by_scene.values()]).format(signed=True)
                 for n, by_scene in curves.items()}
        lines.append("| mean of steps 2+ | " + " | ".join(later[n] for n in curves) + " |")
        lines.append(f"| mean of steps {steps // 2 + 1}-{steps} (later half) | "
                     + " | ".join(late[n].format(signed=True) for n in curves) + " |")
    return "\n".join(lines) + "\n", bands, late


def _extreme(bands: Mapping[str, Sequence[Interval]]) -> str:
    """The largest |mean| of any variant at any step, and the (variant, step) cells whose interval excludes 0."""
    cells = [(abs(i.mean), name, step + 1, i) for name, band in bands.items() for step, i in enumerate(band)]
    size, name, step, interval = max(cells, key=lambda cell: cell[0])
    excluding = [f"{label(n)} step {s + 1}" for n, band in bands.items() for s, i in enumerate(band)
                 if i.n >= MIN_SCENES and (i.low > 0 or i.high < 0)]
    return (f"Largest in size: {label(name)} at step {step}, {interval.format(signed=True)} dB. Cells whose 95% "
            f"interval excludes zero ({MIN_SCENES}+ scenes): {', '.join(excluding) if excluding else 'none'}.")


def fig6(diagnostics: Mapping, variants: Sequence[str], out_dir: Path) -> str:
    """Fig. 6 (the variants of the paper's per-step claims: A, E, F) with 95% bands over scenes, from the
    visited-state curves; ``per_step_intervals.md``, ``per_step_per_scene.csv`` and ``fig6_per_step.png``."""
    shown = [name for name in variants if any(name in pair for pair in PER_STEP_PAIRS)]
    if not shown:
        return ""
    by_scene = {(scene, "held-out"): {label(name): rows[name]["visited"] for name in shown}
                for scene, rows in diagnostics["per_scene"].items()}
    pairs = [(label(a), label(b)) for a, b in PER_STEP_PAIRS if a in shown and b in shown]
    bands = write_per_step_intervals(by_scene, out_dir, "per_step", pairs=pairs)
    mean = {name: [i.mean for i in steps] for name, steps in per_step_intervals(by_scene).items()}
    plot_per_step_quality(mean, out_dir / "fig6_per_step.png", bands=bands)
    return (out_dir / "per_step_intervals.md").read_text()


def _triple(interval: Interval) -> list[float]:
    return [round(x, 4) for x in (interval.mean, interval.low, interval.high)]


def mechanism_figures(held_out: Mapping, per_seed: Sequence[Mapping], variants: Sequence[str], views: Sequence[str],
                      gap_late: Mapping[str, Interval]) -> dict:
    """The run record's figures of whether this scale carries the mechanism, each [mean, 95% low, high] over
    scenes: A's restoration of the held-out clips against its input (``a_minus_input_db``), A's final sample
    against its first clean prediction (``trajectory_final_minus_first_db``: no collapse on the way), the
    exposure gap over the later half of each variant's trajectory (``exposure_gap_late_db``), and per view count
    the largest difference between two distilled students' means with the largest spread (sd) of a variant's
    mean over training seeds (``students_spread_db``)."""
    figures: dict[str, Any] = {"exposure_gap_late_db": {n: _triple(i) for n, i in gap_late.items()}}
    if REFERENCE in variants:
        final = _scene_values(held_out, REFERENCE, "final")
        inputs = _scene_values(held_out, REFERENCE, "input")
        first = {scene: curve[0] for scene, curve in _scene_values(held_out, REFERENCE, "visited").items()}
        figures["a_minus_input_db"] = _triple(paired_interval(final, inputs))
        figures["trajectory_final_minus_first_db"] = _triple(paired_interval(final, first))
    students = [n for n in variants if n != REFERENCE]
    if len(per_seed) > 1 and len(students) > 1:
        spread = {}
        for v in views:
            means = {n: statistics.fmean(_seed_means(per_seed, n, None, "psnr", v)) for n in students}
            seed_sd = max(statistics.stdev(_seed_means(per_seed, n, None, "psnr", v)) for n in students)
            high, low = max(means, key=means.get), min(means, key=means.get)
            spread[v] = {"largest_difference": round(means[high] - means[low], 4), "between": [high, low],
                         "seed_sd": round(seed_sd, 4)}
        figures["students_spread_db"] = spread
    return figures


def diagnostics_markdown(diagnostics: Mapping, variants: Sequence[str], start: str | None = None) -> str:
    """One training seed's diagnostics (``tracegs-report report.kind=diagnostics``): the held-out clip table (with
    ``start``, each student against the Stage-1 adapter's row), each variant's first clean prediction and final
    sample, the exposure gap per step with its later-half mean, and the mechanism figures of the tracegs-replicate run
    record (intervals over scenes)."""
    _, _, gap_late = per_step_table(diagnostics, variants, "visited", "noised")
    first = {n: mean_interval([curve[0] for curve in _scene_values(diagnostics, n, "visited").values()])
             for n in variants}
    trajectory = {n: paired_interval(_scene_values(diagnostics, n, "final"),
                                     {s: c[0] for s, c in _scene_values(diagnostics, n, "visited").items()})
                  for n in variants}
    lines = [f"{diagnostics['clips']} held-out clips of {len(diagnostics['per_scene'])} scenes, conditions "
             f"{', '.join(diagnostics['conditions'])}, {diagnostics['steps']} reverse steps; PSNR (dB) against "
             "ground truth, 95% intervals over scenes.", "", held_out_markdown(diagnostics, variants, start),
             "| variant | first clean prediction | final − first | exposure gap, later half |", "|---|---|---|---|"]
    lines += [f"| {label(n)} | {first[n].format()} | {trajectory[n].format(signed=True)} | "
              f"{gap_late[n].format(signed=True)} |" for n in variants]
    figures = mechanism_figures(diagnostics, [], variants, [], gap_late)
    return "\n".join(lines) + "\n\n" + json.dumps(figures) + "\n"


def privileged_section(gaps: Sequence[Mapping]) -> tuple[list[str], dict]:
    """The privileged gap over training seeds (each scene averaged over the seeds first): its markdown section and
    the run record's ``privileged_gap_db`` (A from R_d - A from R_s: what the pseudo-targets carry beyond A's own
    restoration of R_s), ``f_minus_a_clips_db`` (the student from R_s - A from R_s) and ``f_minus_a_dense_db``
    (the student from R_s - A from R_d), each [mean, 95% low, high] over scenes."""
    gap = {**gaps[0], "per_scene": mean_tree([g["per_scene"] for g in gaps])}
    figures = privileged_figures(gap)
    student = RESTORER_LABELS["tracegs"]
    record = {"privileged_gap_db": _triple(figures["A from R_d - A from R_s (privileged gap)"]),
              "f_minus_a_clips_db": _triple(figures[f"{student} from R_s - A from R_s"]),
              "f_minus_a_dense_db": _triple(figures[f"{student} from R_s - A from R_d"])}
    return ["## The privileged gap (held-out clips)", "", privileged_gap_markdown(gap)], record


# ------------------------------------------------------------------------------------------------ report


def write_replicate_report(out_dir: str | Path, inputs: ReplicateInputs, header: str = "") -> tuple[Path, dict]:
    """``replicate.md`` (+ per-scene CSVs, the Fig. 6 plot with bands) in ``out_dir``; returns its path and the
    run record's figures (the F - A interval per view count, each ordering's verdict)."""
    out_dir = Path(out_dir)
    per_seed = seed_tables(inputs)
    averaged = mean_tree(per_seed)
    views = sorted({v for methods in averaged.values() for by_views in methods.values() for v in by_views}, key=int)
    for seed, table in zip(inputs.seeds, per_seed):
        write_per_scene_csv(table, out_dir / f"per_scene_seed{seed}.csv", column="variant")
    write_per_scene_csv(averaged, out_dir / "per_scene_seed_mean.csv", column="variant")
    rows = [*inputs.variants, PLAIN]
    metrics = measured_metrics(averaged, rows)
    scenes = sorted(averaged)
    lines, figures = [], {}
    for v in views:
        line, gap = instrument(averaged, v)
        lines.append(line)
        if gap is not None:
            figures[f"f_minus_a_{v}views_db"] = [round(x, 4) for x in (gap.mean, gap.low, gap.high)]
            figures[f"f_minus_a_{v}views_half_width_db"] = round(gap.half_width, 4)
    orderings, verdicts = orderings_markdown(per_seed, averaged, set(rows), views, metrics)
    figures["orderings"] = verdicts
    chains = ", ".join(" < ".join(label(name) for name in ordering.chain) for ordering in TABLE3_ORDERINGS)
    sections = [header, f"{len(scenes)} test scenes ({', '.join(scenes)}), training seeds {list(inputs.seeds)}, "
                f"variants {', '.join(label(n) for n in inputs.variants)} (conf/ablation/). Each scene's value is "
                "averaged over the seeds first; intervals are 95% percentile bootstraps over scenes.", "",
                *lines, "", "## Table 3 (deployment)", "",
                "; ".join(f"{label(n)} {inputs.descriptions[n]}" for n in inputs.variants) + ".", "",
                table3_markdown(per_seed, inputs.seeds, averaged, rows, views, metrics),
                "## The paper's orderings", "",
                f"Each adjacent pair of {chains} (Tables 1-3), marked by the 95% "
                f"interval of its paired difference over scenes (holds: above zero; reversed: below; else not "
                f"resolved; fewer than {MIN_SCENES} scenes resolve nothing); read each mark with its spread over "
                "training seeds.", "", orderings]
    diagnostics = [_read(inputs.diagnostics_dirs[s] / "diagnostics.json") for s in inputs.seeds]
    held_out = {**diagnostics[0], "per_scene": mean_tree([d["per_scene"] for d in diagnostics])}
    describe = (f"{held_out['clips']} held-out clips of {len(held_out['per_scene'])} test scenes at the student "
                f"conditions {', '.join(held_out['conditions'])}, the deployment's {held_out['steps']} reverse "
                "steps; PSNR (dB) against ground truth, reference frames excluded; seeds averaged per scene, "
                "95% intervals over scenes.")
    gap_table, gap_bands, gap_late = per_step_table(held_out, inputs.variants, "visited", "noised")
    advantage_table, advantage_bands, _ = per_step_table(held_out, inputs.variants, "teacher", "visited")
    sections += ["## Held-out clips", "", describe, "", held_out_markdown(held_out, inputs.variants)]
    plot = fig6(held_out, inputs.variants, out_dir)
    if plot:
        sections += ["## Fig. 6 (clean-frame PSNR at each reverse step, held-out clips)", "", plot,
                     "Plot: fig6_per_step.png", ""]
    sections += ["## Exposure gap", "",
                 "PSNR of the clean prediction at the variant's own visited state minus at the forward-noised state "
                 "of the same clip at the same t, from the same noise draw (step 1: the same state, so 0). Near zero "
                 "at every step, the states on-policy training supervises are those off-policy training "
                 "supervises: the two cannot differ for the reason the paper gives.", "", gap_table,
                 _extreme(gap_bands), ""]
    if advantage_table:
        sections += ["## Teacher advantage at the student's states", "",
                     "PSNR of the teacher's clean prediction (the Stage-1 adapter on the variant's R_d) minus the "
                     "student's (on R_s), both at the student's own states: what distillation can transfer there.",
                     "", advantage_table, _extreme(advantage_bands), ""]
    figures["exposure_gap_largest_db"] = round(max(abs(i.mean) for b in gap_bands.values() for i in b), 4)
    figures.update(mechanism_figures(held_out, per_seed, inputs.variants, views, gap_late))
    if inputs.privileged_dirs:
        section, privileged = privileged_section([_read(inputs.privileged_dirs[s] / "privileged_gap.json")
                                                  for s in inputs.seeds])
        sections += section
        figures.update(privileged)
    path = out_dir / "replicate.md"
    with atomic_write(path) as tmp:
        tmp.write_text("\n".join(sections))
    return path, figures
