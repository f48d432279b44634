"""Merge evaluation units (from one or many shards) into the results layout of Tables 1/2 and Fig. 6.

Units are the ``units/<scene>/views_<K>.json`` files ``tracegs.eval.scoring`` writes; the merge is
separate so shards of a SLURM array can be merged by ``tracegs-report`` once all of them finished.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from tracegs.deploy.config import METHODS
from tracegs.eval.interval_tables import write_main_intervals, write_per_step_intervals
from tracegs.eval.metrics import mean_metrics
from tracegs.eval.per_step import mean_curves
from tracegs.eval.tables_and_figures import (
    META_KEY,
    METHOD_LABELS,
    plot_per_step_quality,
    write_results_tables,
)
from tracegs.io import write_json_atomic

# A unit scored before its record named its SSIM conventions (then SSIM was torchmetrics' alone).
NOT_RECORDED = "not recorded"


def unit_path(out_dir: str | Path, scene: str, views: int) -> Path:
    return Path(out_dir) / "units" / scene / f"views_{views}.json"

def unit_records(folder: str | Path) -> list[dict]:
    """The records of the evaluation units under ``folder`` (none: an empty list), ordered by scene and K as
    their files are; the merge, the report page and the viewer all read the units this way."""
    return [json.loads(f.read_text()) for f in sorted((Path(folder) / "units").glob("*/views_*.json"))]


def read_units(folder: str | Path) -> dict[tuple[str, int], dict]:
    """The evaluation units under ``folder`` by (scene, K)."""
    units = unit_records(folder)
    if not units:
        raise FileNotFoundError(f"no evaluation units under {Path(folder) / 'units'}")
    return {(u["scene"], int(u["views"])): u for u in units}


def with_methods_from(units: dict[tuple[str, int], dict], sources: Mapping[str, dict[tuple[str, int], dict]]
                      ) -> dict[tuple[str, int], dict]:
    """``units`` with each method of ``sources`` (method -> another evaluation's units) taken from that evaluation:
    its scores and its Fig. 6 curve, unit by unit; a unit that evaluation lacks stays without the method."""
    merged = {}
    for key, unit in units.items():
        unit = {**unit, "methods": dict(unit["methods"]), "per_step": dict(unit.get("per_step") or {})}
        for method, other in sources.items():
            if key in other and method in other[key]["methods"]:
                unit["methods"][method] = other[key]["methods"][method]
                for label in ("lpips", "ssim"):
                    unit[label] = "; ".join(sorted({unit.get(label, NOT_RECORDED), other[key].get(label, NOT_RECORDED)}))
                if method in (other[key].get("per_step") or {}):
                    unit["per_step"][method] = other[key]["per_step"][method]
        merged[key] = unit
    return merged


def view_names(unit: Mapping, kind: str) -> str:
    """The ``kind`` views of a unit record ("captured" or "test") by their images' file names (records written
    before the names were kept: by index)."""
    names = unit.get("names", {})
    views = unit[kind]
    if all(str(view) in names for view in views):
        return ", ".join(names[str(view)] for view in views)
    return f"views {views}"


def merge_results(out_dir: str | Path, scenes: Sequence[str] | None = None, views: Sequence[int] | None = None,
                  methods: Sequence[str] | None = None, sources: Mapping[str, Path] | None = None) -> dict:
    """Merge unit files (from one or many shards) into ``results.json``, ``per_scene.json`` and the table.

    Each (method, K) cell is the unweighted mean over scenes of the per-scene means over test views.
    Every requested scene must have a unit for every requested K, so no cell silently averages fewer
    scenes than another. ``None`` selects whatever units exist. ``sources`` (method -> evaluation folder) takes
    those methods from other evaluations of the same scenes and views (Tables 1/2 from an ablation sweep's).
    """
    out_dir = Path(out_dir)
    by_key = with_methods_from(read_units(out_dir), {m: read_units(f) for m, f in (sources or {}).items()})
    units = list(by_key.values())
    scenes = sorted({u["scene"] for u in units}) if scenes is None else list(scenes)
    views = sorted({int(u["views"]) for u in units}) if views is None else [int(v) for v in views]
    missing = [f"{s}/views_{k}" for s in scenes for k in views if (s, k) not in by_key]
    if missing:
        raise FileNotFoundError(f"{out_dir / 'units'}: missing evaluation units {missing} (shards not finished?)")
    chosen = [by_key[(s, k)] for s in scenes for k in views]
    if methods is None:
        methods = [m for m in METHODS if all(m in u["methods"] for u in chosen)]
    lacking = [f"{m} ({sources[m] if m in (sources or {}) else out_dir})" for m in methods
               if not all(m in u["methods"] for u in chosen)]
    if lacking:
        raise FileNotFoundError(f"evaluation.methods: no scores of {', '.join(lacking)} for every scene and view "
                                "count (run tracegs-evaluate for them first)")
    lpips_labels = sorted({u["lpips"] for u in chosen})
    ssim_labels = sorted({u.get("ssim", NOT_RECORDED) for u in chosen})
    variants = sorted({u.get("variant") for u in chosen}, key=str)
    results: dict = {}
    per_scene: dict = {s: {} for s in scenes}
    for method in methods:
        results[method] = {}
        for k in views:
            scene_means = [by_key[(s, k)]["methods"][method]["mean"] for s in scenes]
            results[method][str(k)] = mean_metrics(scene_means)
            for s, mean in zip(scenes, scene_means):
                per_scene[s].setdefault(method, {})[str(k)] = mean
    results[META_KEY] = {
        "lpips": "; ".join(lpips_labels),
        "ssim": "; ".join(ssim_labels),
        "scenes": list(scenes),
        "variant": variants[0] if len(variants) == 1 else variants,
        "protocol": "mean over each scene's test views (captured views excluded), then unweighted mean over scenes",
    }
    if sources:
        results[META_KEY]["methods_from"] = {m: os.path.relpath(folder, out_dir) for m, folder in sources.items()}
    write_json_atomic(results, out_dir / "results.json")
    write_json_atomic(per_scene, out_dir / "per_scene.json")
    unit_curves = {(u["scene"], str(u["views"])): u["per_step"] for u in chosen if u.get("per_step")}
    if unit_curves:
        # Fig. 6 protocol: averaged across view settings (and scenes), before 3DGS refinement.
        mean = mean_curves(list(unit_curves.values()))
        write_json_atomic(mean, out_dir / "per_step.json")
        bands = write_per_step_intervals(unit_curves, out_dir, "per_step", pairs=[("tracegs", "baseline")])
        plot_per_step_quality({METHOD_LABELS.get(m, m): c for m, c in mean.items()}, out_dir / "fig6_per_step.png",
                              bands={METHOD_LABELS.get(m, m): band for m, band in bands.items()})
    write_results_tables(results, out_dir, stem="table", views=[str(k) for k in views])
    write_main_intervals(per_scene, out_dir, [str(k) for k in views])
    return results
