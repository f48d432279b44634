"""Replicates over seeds: the demo's tables as mean, standard deviation and range over independent runs.

A run folder of ``tracegs-demo`` holds ``results.json`` (deployment, Tables 1/2 layout),
``held_out_clips.json`` (restorer output vs its input R_s), ``per_step.json`` (Fig. 6 curves) and
``run.json`` (commit, seed, machine). :func:`demo_summary` flattens one folder into named figures;
:func:`seed_spread_markdown` states each figure over several folders.
"""

from __future__ import annotations

import json
import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path

from tracegs.eval.tables_and_figures import METHOD_LABELS, methods_in

PER_STEP_POINTS = ("first", "min", "final")


def per_step_points(curve: Sequence[float]) -> dict[str, float]:
    """Fig. 6 in three numbers: the first step's clean-frame PSNR, the lowest along the way, the final one."""
    return {"first": curve[0], "min": min(curve), "final": curve[-1]}


def _read(folder: Path, name: str) -> dict:
    path = folder / name
    return json.loads(path.read_text()) if path.is_file() else {}


def demo_summary(folder: str | Path) -> dict[str, dict[str, float]]:
    """Figures of one demo run, grouped by table: {table: {row | column: value}}."""
    folder = Path(folder)
    if not (folder / "results.json").is_file():
        raise FileNotFoundError(f"report.inputs: {folder} has no results.json (not a tracegs-demo run folder)")
    results = _read(folder, "results.json")
    tables: dict[str, dict[str, float]] = {"deployment PSNR": {}, "deployment SSIM": {}}
    for method in methods_in(results):
        for views, row in results[method].items():
            label = f"{METHOD_LABELS.get(method, method)}, {views} views"
            tables["deployment PSNR"][label] = row["psnr"]
            tables["deployment SSIM"][label] = row["ssim"]
    held_out = _read(folder, "held_out_clips.json")
    if held_out:
        tables["held-out clips PSNR"] = {
            f"{'input R_s' if m == 'input' else METHOD_LABELS.get(m, m)}, {condition}": value
            for condition, row in [*held_out["conditions"].items(), ("mean", held_out["mean"])]
            for m, value in row.items()}
    curves = _read(folder, "per_step.json")
    if curves:
        tables["Fig. 6 per-step PSNR"] = {
            f"{METHOD_LABELS.get(m, m)}, {point}": value
            for m, curve in curves.items() for point, value in per_step_points(curve).items()}
    return tables


def seed_spread_markdown(folders: Sequence[str | Path]) -> str:
    """Each figure of the demo over seed replicates: mean, standard deviation, range and every seed's value."""
    summaries = [demo_summary(f) for f in folders]
    runs = [_read(Path(f), "run.json") for f in folders]
    seeds = [str(r.get("seed", "?")) for r in runs]
    lines = [f"Over {len(folders)} seeds ({', '.join(seeds)}); commits "
             f"{', '.join(sorted({r.get('commit', 'unknown') for r in runs}))}; "
             f"machine: {machine_line(runs)}.", ""]
    for table in summaries[0]:
        lines += [f"### {table}", "",
                  "| row | mean | sd | min | max | " + " | ".join(f"seed {s}" for s in seeds) + " |",
                  "|" + "---|" * (5 + len(seeds))]
        for label in summaries[0][table]:
            values = [s.get(table, {}).get(label) for s in summaries]
            present = [v for v in values if v is not None]
            sd = statistics.stdev(present) if len(present) > 1 else float("nan")
            cells = [label, figure(statistics.fmean(present)), figure(sd), figure(min(present)), figure(max(present))]
            lines.append("| " + " | ".join(cells + [figure(v) for v in values]) + " |")
        lines.append("")
    return "\n".join(lines)


def figure(value: float | None) -> str:
    if value is None or value != value:
        return "n/a"
    return f"{value:.3f}" if abs(value) < 2 else f"{value:.2f}"


def machine_line(runs: Sequence[Mapping]) -> str:
    machines = {json.dumps(r.get("machine", {}), sort_keys=True) for r in runs}
    described = [json.loads(m) for m in machines]
    return "; ".join(f"{m.get('cpu', '?')} ({m.get('cores', '?')} cores, torch {m.get('torch', '?')})"
                     for m in described)
