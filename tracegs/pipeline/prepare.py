"""``tracegs-prepare``: generate the synthetic benchmark if selected, then build the paired-clip cache."""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig

from tracegs.data.prepare import require_inputs, run_prepare
from tracegs.data.sources import SceneSource
from tracegs.devices import accelerator
from tracegs.pipeline.records import check_run_record, product_lock, write_run_record
from tracegs.pipeline.upstream import section
from tracegs.restorer.build import build_backbone

log = logging.getLogger("tracegs")


def prepare(cfg: DictConfig) -> Path:
    """Generate the synthetic benchmark if selected, then build the paired-clip cache."""
    require_inputs(section(cfg.data.prepare))  # before the backbone loads: bad settings cost nothing
    check_run_record(cfg, "prepare", cfg.data.prepare.cache_dir)
    shard = (cfg.data.prepare.shard_index, cfg.data.prepare.num_shards)
    with product_lock(cfg.data.prepare.cache_dir, "data.prepare.cache_dir", shard):
        backbone = build_backbone(section(cfg.backbone), device=accelerator())
        scenes = SceneSource.of(cfg.data)
        manifest = run_prepare(section(cfg.data.prepare), scenes.source, backbone, scenes.procedural)
        write_run_record(cfg, "prepare", cfg.data.prepare.cache_dir)
    log.info("paired-clip cache: %s", manifest)
    return manifest
