"""``tracegs-train``: one training stage (A, Stage 1 or Stage 2) into its run folder, reused when finished."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from omegaconf import DictConfig

from tracegs.data.sources import SceneSource
from tracegs.eval.held_out_curve import HELD_OUT_CURVE
from tracegs.pipeline.records import product_lock, reuse_finished, write_run_record
from tracegs.pipeline.upstream import locate_artifacts, section
from tracegs.products import BASELINE
from tracegs.stages import stage_table
from tracegs.training.config import TrainConfig
from tracegs.training.run import train_stage

log = logging.getLogger("tracegs")


def train(cfg: DictConfig) -> Path | None:
    """Train ``cfg.stage.name`` into ``cfg.run_dir``; a variant that trains no student (A) trains no Stage 2."""
    stage = stage_table().stage(cfg.stage.name)
    if stage.per_variant and not cfg.ablation.train_stage2:
        log.info("ablation %s is the frozen baseline restorer: %s has nothing to train", cfg.ablation.name,
                 stage.product)
        return None
    if cfg.stage.name == BASELINE and cfg.experiment.baseline_steps == 0:
        # Paper scale: variant A is GSFixer's pretrained restorer, loaded where it is used; the sweep's first
        # command must pass on to Stage 1 rather than stop.
        log.info("experiment %s: variant A is the pretrained restorer %s; nothing to train", cfg.experiment.name,
                 cfg.backbone.transformer.pretrained_path)
        return None
    locate_artifacts(cfg, stage_table().stage_inputs(stage.product))
    product = Path(cfg.run_dir) / stage.folder
    with product_lock(cfg.run_dir, "run_dir"):
        if reuse_finished(cfg, cfg.stage.name, cfg.run_dir, product):
            return product
        return train_locked(cfg)


def train_and_validate(cfg: DictConfig) -> float | None:
    """``train``, then the trained adapter's held-out clip PSNR on ``stage.held_out_eval.cache`` at its last step
    (the validation scenes' cache, ``tracegs-prepare data.prepare.split=val``): the metric a hyperparameter
    search maximises (``hparams_search=``, Optuna through Hydra's sweeper); None without a held-out cache. A
    finished run is not trained again: its recorded curve gives the metric."""
    train(cfg)
    if cfg.stage.held_out_eval.cache is None:
        return None
    curve = Path(cfg.run_dir) / HELD_OUT_CURVE
    if not curve.is_file():
        raise FileNotFoundError(f"stage.held_out_eval.cache: {curve} was not written; the run finished before the "
                                "held-out cache was named, so train it again in a fresh run_dir")
    return float(json.loads(curve.read_text())["points"][-1]["mean"])


def train_locked(cfg: DictConfig) -> Path:
    """Train (or resume) ``cfg.stage.name`` in its run folder, whose lock this process holds."""
    train_cfg = TrainConfig(
        stage=section(cfg.stage),
        optimizer=section(cfg.optimizer),
        loss=section(cfg.loss),
        teacher=section(cfg.teacher),
        policy=section(cfg.policy),
        trainer=section(cfg.trainer),
        backbone=section(cfg.backbone),
        data=section(cfg.data.datamodule),
        output_dir=cfg.run_dir,
        source=section(cfg.data.source),
        deploy=section(cfg.deploy),
        fit=section(cfg.data.prepare.fit),
    )
    if train_cfg.stage.deployment_eval.scenes:
        SceneSource.of(cfg.data).generate(("val",), progress=False)  # the validation scenes
    product = train_stage(train_cfg)
    write_run_record(cfg, cfg.stage.name, cfg.run_dir)
    log.info("%s product: %s", cfg.stage.name, product)
    return product
