"""``tracegs-prepare``: generate the synthetic benchmark if selected, then build the paired-clip cache."""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from tracegs.data.config import PseudoTarget, as_prepared, is_procedural
from tracegs.data.preparation.driver import run_prepare
from tracegs.data.preparation.plan import require_inputs
from tracegs.data.sources import SceneSource
from tracegs.devices import accelerator
from tracegs.pipeline.records import check_run_record, product_lock, write_run_record
from tracegs.pipeline.upstream import locate_artifacts, section
from tracegs.restorer.build import build_backbone
from tracegs.stages import Product, stage_table

log = logging.getLogger("tracegs")


def prepare(cfg: DictConfig) -> Path:
    """Generate the synthetic benchmark if selected, then build the paired-clip cache."""
    require_inputs(section(cfg.data.prepare))  # before the backbone loads: bad settings cost nothing
    generator = pseudo_target_generator(cfg)  # located first: its content is part of the cache's record
    check_run_record(cfg, "prepare", cfg.data.prepare.cache_dir)
    shard = (cfg.data.prepare.shard_index, cfg.data.prepare.num_shards)
    with product_lock(cfg.data.prepare.cache_dir, "data.prepare.cache_dir", shard):
        backbone_cfg = section(cfg.backbone)
        if generator is not None:
            backbone_cfg.transformer.pretrained_path = str(generator)
        backbone = build_backbone(backbone_cfg, device=accelerator())
        scenes = SceneSource.of(cfg.data)
        manifest = run_prepare(section(cfg.data.prepare), scenes.source, backbone, scenes.procedural)
        write_run_record(cfg, "prepare", cfg.data.prepare.cache_dir)
    log.info("paired-clip cache: %s", manifest)
    return manifest


def pseudo_target_generator(cfg: DictConfig) -> Path | None:
    """The transformer that restores R_d into this cache's pseudo-targets (supplement, "Pseudo-target
    generation"): ``data.prepare.pseudo_target_weights``, variant A's product located by its identity where it
    interpolates ``artifacts.baseline_weights`` (the embedded scale); None where the cache's clips need no
    restorer or the backbone's own pretrained weights are the generator (paper scale: GSFixer). Refused in one
    line when the located product is missing."""
    prepared = as_prepared(section(cfg.data.prepare), is_procedural(cfg.data.source))
    if prepared.pseudo_target != PseudoTarget.restorer or cfg.data.prepare.pseudo_target_weights is None:
        return None
    # The cache is named before A is located: A's settings name it (tracegs.config.identity), not A's path.
    for key in ("data.prepare.cache_dir", "data.prepare.work_dir"):
        OmegaConf.update(cfg, key, str(OmegaConf.select(cfg, key)))
    locate_artifacts(cfg, stage_table().record_inputs(Product.prepare))
    weights = Path(str(cfg.data.prepare.pseudo_target_weights))
    if not weights.is_dir():
        raise FileNotFoundError(
            f"data.prepare.pseudo_target_weights: no pretrained restorer at {weights} (its pseudo-targets come from "
            "variant A: run `tracegs-prepare data.prepare.split=pretrain`, then `tracegs-train stage=baseline`)")
    log.info("pseudo-targets: the frozen restorer %s on R_d", weights)
    return weights
