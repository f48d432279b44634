"""``tracegs-evaluate`` and ``tracegs-deploy``: restore-refine deployment of the test scenes."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from omegaconf import DictConfig

from tracegs.data.cache_keys import MANIFEST
from tracegs.deploy.scenes import deploy_scenes
from tracegs.eval.clips import clip_restoration_psnr
from tracegs.eval.html_report import write_report_page
from tracegs.eval.scoring import score_units
from tracegs.eval.tables_and_figures import write_held_out_report
from tracegs.io import bytes_digest
from tracegs.pipeline.records import check_run_record, product_lock, write_run_record
from tracegs.pipeline.restorers import (
    generate_test_scenes,
    ground_truth_renderer,
    locate_deployed_artifacts,
    restorers_for_run,
    test_scenes,
)
from tracegs.pipeline.upstream import section
from tracegs.splat.render import require_available

log = logging.getLogger("tracegs")


def evaluate(cfg: DictConfig) -> dict:
    """Deploy every method on the test scenes at each view count; write results.json (+ tables, media)."""
    require_available(cfg.data.prepare.fit.backend, "data.prepare.fit.backend")
    scenes = test_scenes(cfg)  # worked out (and checked held out) once, before any restorer is loaded
    # A folder holding another run's evaluation is refused before minutes of loading weights; its record names
    # the restorers by path, so they are located first.
    locate_deployed_artifacts(cfg)
    finished = check_run_record(cfg, "evaluate", cfg.evaluation.out_dir)
    restorers = restorers_for_run(cfg, list(cfg.evaluation.methods))
    generate_test_scenes(cfg)
    shard = (cfg.evaluation.shard_index, cfg.evaluation.num_shards)
    with product_lock(cfg.evaluation.out_dir, "evaluation.out_dir", shard):
        results = score_units(
            section(cfg.evaluation),
            section(cfg.data.source),
            section(cfg.deploy),
            section(cfg.data.prepare.fit),
            restorers,
            scenes=scenes,
            gt_renderer=ground_truth_renderer(cfg),
        )
        if cfg.evaluation.held_out_cache is not None:
            held_out_quality(cfg, restorers, finished)
        if cfg.evaluation.num_shards == 1:  # a shard's page waits for the merge (tracegs-report report.kind=main)
            write_report_page(cfg.evaluation.out_dir)
        write_run_record(cfg, "evaluate", cfg.evaluation.out_dir)
    log.info("evaluation written to %s", cfg.evaluation.out_dir)
    return results


def held_out_quality(cfg: DictConfig, restorers: dict, finished: bool = False) -> Path:
    """Score each diffusion restorer against its input R_s on the held-out clips (eval/clips.py).

    A finished score is a product. In a ``finished`` evaluation folder (its record holds these settings and the
    restorers' contents) the score records the held-out cache's manifest, the seed and the methods it was made
    from, so a rerun with the same ones keeps it (minutes of restoration) and anything else scores again."""
    pipelines = {method: r.pipeline for method, r in restorers.items() if r is not None}
    made_from = {"held_out_manifest": bytes_digest(Path(cfg.evaluation.held_out_cache) / MANIFEST),
                 "seed": cfg.deploy.seed, "methods": sorted(pipelines)}
    scored = Path(cfg.evaluation.out_dir) / "held_out_clips.json"
    if finished and scored.is_file() and json.loads(scored.read_text()).get("made_from") == made_from:
        log.info("held-out clip quality: made from the same clips, seed and restorers, kept (%s)", scored)
        return scored.with_suffix(".md")
    quality = clip_restoration_psnr(pipelines, cfg.evaluation.held_out_cache, seed=cfg.deploy.seed,
                                    progress=cfg.evaluation.progress)
    table = write_held_out_report({**quality, "made_from": made_from}, cfg.evaluation.out_dir)
    log.info("held-out clip quality: %s", table)
    return table


def deploy(cfg: DictConfig) -> list[Path]:
    """Restore-refine each test scene at each view count with the selected restorer; save refined PLYs."""
    require_available(cfg.data.prepare.fit.backend, "data.prepare.fit.backend")
    scenes = test_scenes(cfg)
    method = "tracegs" if cfg.ablation.train_stage2 else "baseline"
    locate_deployed_artifacts(cfg)
    check_run_record(cfg, "deploy", cfg.run_dir)
    restorer = restorers_for_run(cfg, [method])[method]
    generate_test_scenes(cfg)
    with product_lock(cfg.run_dir, "run_dir", (cfg.evaluation.shard_index, cfg.evaluation.num_shards)):
        written = deploy_scenes(section(cfg.evaluation), section(cfg.data.source), section(cfg.deploy),
                                section(cfg.data.prepare.fit), restorer, scenes, cfg.run_dir)
        write_run_record(cfg, "deploy", cfg.run_dir)
    return written
