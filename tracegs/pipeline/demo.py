"""``tracegs-demo``: the whole pipeline (tracegs.pipeline.steps) in this process on the composed experiment,
ending with the tables it produced."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path

from omegaconf import DictConfig

from tracegs.console import LogBookmark, show
from tracegs.devices import require_trainer_device
from tracegs.eval.html_report import write_report_page
from tracegs.eval.seeds import per_step_points
from tracegs.eval.tables_and_figures import results_table_markdown
from tracegs.io import atomic_write, bytes_digest, write_json_atomic
from tracegs.pipeline.evaluate import evaluate
from tracegs.pipeline.prepare import prepare
from tracegs.pipeline.runner import InProcess, Step, run_steps
from tracegs.pipeline.steps import (
    HELD_OUT_CACHE,
    HELD_OUT_SPLIT,
    baseline_steps,
    data_steps,
    in_protocol_order,
    restorer_steps,
)
from tracegs.pipeline.train import train
from tracegs.provenance import describe, peak_rss_gib

log = logging.getLogger("tracegs")

TASKS = {"prepare": prepare, "train": train, "evaluate": evaluate}
# The evaluation's files the demo's tables are made of (demo_tables_markdown).
TABLE_SOURCES = ("results.json", "per_scene.json", "intervals.md", "held_out_clips.json", "held_out_clips.md",
                 "per_step.json", "per_step_intervals.md")


def demo_steps(variant: str, views: Sequence[int], out_dir: Path, pretrain: bool = True) -> list[Step]:
    """The demo's steps (``pretrain``: A on its own pretraining scenes first, experiment.baseline_split). The test
    scenes are prepared (held-out clips) and deployed at ``views`` input views only (the demo's ``evaluation.views``); the training clips keep every student view count. The evaluation
    writes into ``out_dir`` and reads the held-out cache the test prepare hands on; that cache holds no teacher R_d
    (the held-out clips score restorers from R_s only; ``report.kind=privileged`` needs a cache with one)."""
    views = list(views)
    data = data_steps(held_out={"data.prepare.student_views": views, "data.prepare.dense_views": []})
    return [*in_protocol_order(pretrain, baseline_steps(pretrain), data),
            *restorer_steps(variant, evaluation={**HELD_OUT_SPLIT, "evaluation.views": views,
                                                 "evaluation.save_models": True, "evaluation.out_dir": out_dir},
                            evaluation_takes={"evaluation.held_out_cache": HELD_OUT_CACHE})]


def demo(cfg: DictConfig) -> Path:
    """The whole pipeline on the composed experiment: prepare -> A -> Stage 1 -> Stage 2 (the configured
    variant) -> evaluation.

    The evaluation writes straight into the demo's folder (tables, held-out clips, Fig. 6, grids, videos,
    refined PLYs); the demo adds ``run.json`` (commit, seed, machine, timings), ``tables.md`` and the page showing
    them all (``report.html``, tracegs.eval.html_report).
    """
    require_trainer_device(cfg.trainer.accelerator)  # its training steps come after minutes of preparation
    start = time.perf_counter()
    bookmark = LogBookmark()
    out_dir = Path(cfg.run_dir)
    steps = demo_steps(cfg.ablation.name, cfg.evaluation.views, out_dir, cfg.experiment.baseline_split == "pretrain")
    timings = run_steps(steps, InProcess(cfg, TASKS), "demo")
    products = {name: bytes_digest(out_dir / name) for name in TABLE_SOURCES if (out_dir / name).is_file()}
    record = out_dir / "run.json"
    earlier = json.loads(record.read_text()) if record.is_file() else None
    if earlier is not None and earlier.get("products") == products:
        # Nothing the tables show was made again: run.json and the log keep how the products were made (the first
        # run's commit, machine and timings), not how long it took to find them finished.
        # The evaluation step above wrote report.html from these same files (tracegs.eval.html_report), so a root
        # finished before the page existed has it now, and a later rerun writes the same bytes.
        bookmark.rewind()
        print((out_dir / "tables.md").read_text())
        print(f"tracegs-demo: every product was already made ({earlier['wall_s']:.0f} s on commit "
              f"{earlier['commit']}, recorded in run.json and the log); nothing recomputed in "
              f"{time.perf_counter() - start:.0f} s", flush=True)
        return out_dir
    run = {**describe(cfg.seed), "wall_s": round(time.perf_counter() - start, 1),
           "peak_rss_gib": round(peak_rss_gib(), 3), "step_s": timings, "products": products}
    if earlier is not None:  # part of the products made again: this run's figures, beside the earlier runs'
        run["earlier"] = [*earlier.pop("earlier", []), earlier]
    write_json_atomic(run, record)
    with atomic_write(out_dir / "tables.md") as tmp:
        tmp.write_text(demo_tables_markdown(out_dir, run))
    page = write_report_page(out_dir)
    show((out_dir / "tables.md").read_text())
    show(f"tracegs-demo: finished in {run['wall_s']:.0f} s, peak RSS {run['peak_rss_gib']:.2f} GiB")
    show(f"tracegs-demo: tables, grids, videos, refined PLYs and plots in {out_dir.resolve()}")
    show(f"tracegs-demo: all of them on one page: {page.resolve()}")
    return out_dir


def demo_tables_markdown(out_dir: Path, run: dict) -> str:
    """The demo's tables, ready to paste, headed by the run that produced them."""
    machine = run["machine"]
    lines = [f"Commit {run['commit']}, seed {run['seed']}, {machine['cpu']} ({machine['cores']} cores, "
             f"torch {machine['torch']}): {run['wall_s'] / 60:.1f} min, peak RSS {run['peak_rss_gib']:.2f} GiB.", "",
             "Deployment on the test scenes:", "",
             results_table_markdown(json.loads((out_dir / "results.json").read_text()))]
    intervals = out_dir / "intervals.md"
    if intervals.is_file():
        scenes = len(json.loads((out_dir / "per_scene.json").read_text()))
        lines += [f"The same with 95% intervals over its {scenes} test scenes (with this few scenes the intervals "
                  "are wide; `make replicate` runs enough scenes and seeds to resolve smaller gaps):", "",
                  intervals.read_text()]
    held_out = out_dir / "held_out_clips.md"
    if held_out.is_file():
        lines += ["Held-out clips (is the restorer's output closer to ground truth than its input R_s?):", "",
                  held_out.read_text()]
    per_step = out_dir / "per_step.json"
    if per_step.is_file():
        lines += ["Fig. 6, clean-frame prediction along the restorer's own trajectory (PSNR, dB):", "",
                  "| method | first step | minimum | final |", "|---|---|---|---|"]
        for method, curve in json.loads(per_step.read_text()).items():
            points = per_step_points(curve)
            lines.append(f"| {method} | " + " | ".join(f"{points[p]:.2f}" for p in ("first", "min", "final")) + " |")
        lines.append("")
        if (out_dir / "per_step_intervals.md").is_file():
            lines += [(out_dir / "per_step_intervals.md").read_text()]
    return "\n".join(lines)
