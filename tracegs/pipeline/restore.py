"""``tracegs-restore``: restore and refine a capture of the user's own (Algorithm 1, bottom): a COLMAP scene, or
photos or a video that structure-from-motion reconstructs first (tracegs.data.sfm)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import torch
from omegaconf import DictConfig

from tracegs.console import show
from tracegs.data.sfm import reconstruct_photos, reconstruct_video
from tracegs.data.splits import SplitError
from tracegs.errors import ConfigError
from tracegs.eval.html_report import write_report_page
from tracegs.eval.merge import unit_path, view_names
from tracegs.eval.scoring import score_units
from tracegs.eval.tables_and_figures import results_table_markdown
from tracegs.pipeline.records import product_lock
from tracegs.pipeline.restorers import restorers_for_run
from tracegs.pipeline.upstream import section


def scene_folder(cfg: DictConfig) -> Path:
    """The COLMAP scene folder (images/ + sparse/0) the capture is: ``capture.path`` itself when it holds a
    reconstruction, else the one structure-from-motion makes of its photos, or of ``capture.video``'s frames."""
    if cfg.capture.path is not None and cfg.capture.video is not None:
        raise ConfigError("capture.video", "set either capture.path (a scene or photo folder) or capture.video, "
                                           "not both")
    sfm, test_every = section(cfg.capture.sfm), cfg.data.source.test_every
    if cfg.capture.video is not None:
        video = Path(cfg.capture.video).expanduser().resolve()
        return reconstruct_video(video, cfg.capture.frames, sfm, cfg.capture.views, test_every)
    if cfg.capture.path is None:
        raise ValueError("capture.path: name the COLMAP scene folder or the folder of photos to restore, e.g. "
                         "tracegs-restore capture.path=/data/my_scene (or capture.video=<file>)")
    capture = Path(cfg.capture.path).expanduser().resolve()
    if not capture.is_dir():
        raise FileNotFoundError(f"capture.path: {capture} is not a directory")
    if (capture / "sparse").is_dir():
        return capture
    return reconstruct_photos(capture, sfm, cfg.capture.views, test_every)


def restore(cfg: DictConfig) -> Path:
    """Restore and refine a capture of your own from K of its views (Algorithm 1, bottom), next to plain 3DGS,
    scored on the views it left out; the evaluation writes the PLYs, the grid and the video."""
    capture = scene_folder(cfg)
    if not torch.cuda.is_available():
        # One unit of small tensors runs in this process: more intra-op threads only spin (on a shared
        # 2-core machine 2 threads cost 2.5x the CPU time of 1 for the same run).
        torch.set_num_threads(1)
    # The capture is one scene folder: its parent is the dataset root the COLMAP loader reads scenes from.
    source = replace(section(cfg.data.source), root=str(capture.parent), scenes=[capture.name])
    evaluation = section(cfg.evaluation)
    with product_lock(evaluation.out_dir, "evaluation.out_dir"):
        try:
            results = score_units(evaluation, source, section(cfg.deploy), section(cfg.data.prepare.fit),
                                  restorers_for_run(cfg, evaluation.methods), scenes=[capture.name])
        except SplitError as error:  # the user chose the count: capture.views
            raise ConfigError("capture.views", f"{cfg.capture.views}: {capture}: {error}; ask for fewer views or "
                                               "capture more images") from error
        page = write_report_page(evaluation.out_dir)
    unit = json.loads(unit_path(evaluation.out_dir, capture.name, cfg.capture.views).read_text())
    out = Path(evaluation.out_dir).resolve()  # the unit names its files relative to the evaluation folder
    show(results_table_markdown(results, views=[str(cfg.capture.views)]))
    show(f"\n{capture.name}: fitted from {view_names(unit, 'captured')}, scored on held-out {view_names(unit, 'test')}")
    for method, ply in unit["models"].items():
        show(f"refined 3DGS ({method}): {out / ply}")
    show(f"grid: {out / unit['media']['grid']}\nvideo: {out / unit['media']['video']}")
    for method, frames in unit["media"].get("frames", {}).items():
        show(f"trajectory renders ({method}): {out / frames}/")
    show(f"report: {page.resolve()}")
    return out / unit["models"][evaluation.methods[-1]]
