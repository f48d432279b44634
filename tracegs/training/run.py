"""``train_stage(cfg)``: build backbone, data, stage module and a ``lightning.Trainer``, train, export.

Outputs under ``cfg.output_dir``: ``checkpoints/`` (resumable Lightning checkpoints, trainable weights
only), ``csv/version_<k>/metrics.csv`` (one version per start) and ``tensorboard/`` logs, and the stage's product
in the folder the stage table names (tracegs.stages), written by the stage's LightningModule (``export``):
- baseline: ``baseline_transformer/`` -- a diffusers directory with the full tiny transformer, to be set as
  ``backbone.transformer.pretrained_path`` for Stage 1, Stage 2 and deployment (variant A);
- stage1: ``stage1_adapter/`` (the aligned adapter phi, a peft adapter folder);
- stage2: ``student_adapter/`` (phi_S, the only thing deployment loads; ``PeftModel.from_pretrained`` reads it).
With ``stage.deployment_eval`` naming validation scenes, the loggers also hold the deployed restorer's scores
(``deploy/psnr_k3`` ..., tracegs/eval/callback.py).
"""

from __future__ import annotations

import copy
import signal
from importlib import import_module
from pathlib import Path

import lightning as L
from lightning.pytorch.callbacks import Callback, EMAWeightAveraging
from lightning.pytorch.loggers import CSVLogger, Logger, TensorBoardLogger
from lightning.pytorch.plugins.environments import SLURMEnvironment
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf

from tracegs.console import interactive, quiet_library_notices
from tracegs.data.datamodule import MANIFEST, NO_TEACHER, PairedClipDataModule
from tracegs.devices import require_trainer_device
from tracegs.errors import ConfigError, require_writable_dir
from tracegs.eval.callback import DeploymentRefinement, ModuleRestorerFactory
from tracegs.eval.held_out_curve import HeldOutClipQuality
from tracegs.processes import sigterm_at_its_default
from tracegs.restorer.build import build_backbone
from tracegs.stages import stage_table
from tracegs.training.attention import AttentionKernelCheck
from tracegs.training.checkpoints import (
    CheckpointOnSignal,
    ConfirmedCheckpoint,
    finished_checkpoint_state,
    keep_newest_requeue_checkpoint,
    newest_checkpoint,
    requeue_checkpoints,
    require_loadable_checkpoint,
    stopped_by_signal,
)
from tracegs.training.config import StageConfig, TrainConfig
from tracegs.training.module import RestorerTrainingModule
from tracegs.training.progress import PlainTrainingProgress
from tracegs.training.strategy import build_strategy, full_lora_state, one_job_of_processes


def stage_module(name: str) -> type[RestorerTrainingModule]:
    """The LightningModule class that trains the stage ``name``: its row of the stage table names it
    (tracegs.stages), imported here, where it is trained."""
    module, _, cls = stage_table().stage(name).module.partition(":")
    return getattr(import_module(module), cls)


def build_module(cfg: TrainConfig, backbone) -> RestorerTrainingModule:
    """The LightningModule of ``cfg.stage.name`` around the backbone's transformer and schedule."""
    return stage_module(cfg.stage.name).of(cfg, backbone)


def build_loggers(cfg: TrainConfig, output_dir: Path) -> list[Logger]:
    loggers: list[Logger] = []
    for name in cfg.trainer.loggers:
        if name == "csv":
            # A new version folder per (re)start: Lightning's CSV writer deletes an existing metrics.csv.
            loggers.append(CSVLogger(output_dir, name="csv"))
        elif name == "tensorboard":
            # One folder across restarts: TensorBoard appends event files, so resumed curves continue.
            loggers.append(TensorBoardLogger(output_dir, name="tensorboard", version=""))
        elif name == "wandb":
            from lightning.pytorch.loggers import WandbLogger  # optional dependency

            loggers.append(WandbLogger(save_dir=str(output_dir), name=f"{cfg.stage.name}"))
        else:
            raise ValueError(f"trainer.loggers: unknown logger {name!r} (csv, tensorboard, wandb)")
    return loggers


def weight_average(stage: StageConfig) -> list[Callback]:
    """The moving average of the baseline's weights (``stage.ema_decay``), copied into the module when training
    ends so the exported product is the average. Lightning's callback writes the average as the checkpoint's
    ``state_dict`` and the current weights beside it, so a resumed run continues both exactly."""
    if stage.ema_decay is None:
        return []
    return [EMAWeightAveraging(decay=stage.ema_decay)]


def deployment_eval(cfg: TrainConfig, backbone, module: RestorerTrainingModule) -> list[Callback]:
    """The deployment-refinement callback when ``stage.deployment_eval`` names validation scenes."""
    settings = cfg.stage.deployment_eval
    if not settings.scenes:
        return []
    factory = ModuleRestorerFactory(backbone, module.deployed_adapter, cfg.deploy.clip_batch, cfg.deploy.steps)
    return [DeploymentRefinement(settings.scenes, cfg.source, factory, cfg.deploy, cfg.fit, views=settings.views,
                                 every_n_steps=settings.every_n_steps, lpips=settings.lpips)]


def held_out_eval(cfg: TrainConfig, backbone, module: RestorerTrainingModule, output_dir: Path) -> list[Callback]:
    """The held-out learning-curve callback when ``stage.held_out_eval.cache`` names a prepared cache."""
    settings = cfg.stage.held_out_eval
    if settings.cache is None:
        return []
    adapter = module.deployed_adapter
    if adapter is None:
        raise ValueError(f"stage.held_out_eval: scores a trained adapter, and stage={cfg.stage.name} trains none; "
                         f"set it to null for stage={cfg.stage.name}")
    if not (Path(settings.cache) / MANIFEST).is_file():
        raise ConfigError("stage.held_out_eval.cache", f"no prepared cache at {settings.cache} (tracegs-prepare "
                                                       "data.prepare.split=val prints the folder it writes)")
    return [HeldOutClipQuality(backbone, adapter, settings.cache, output_dir, settings.every_n_steps,
                               seed=cfg.deploy.seed)]


def build_trainer(cfg: TrainConfig, output_dir: Path, module: RestorerTrainingModule,
                  extra_callbacks: list[Callback] = ()) -> L.Trainer:
    checkpoints = ConfirmedCheckpoint(
        dirpath=output_dir / "checkpoints",
        filename="step{step:06d}",
        auto_insert_metric_name=False,
        every_n_train_steps=cfg.stage.checkpoint_every_n_steps,
        save_top_k=cfg.stage.keep_checkpoints,
        save_last=True,
        enable_version_counter=False,  # one file per step: a rerun overwrites, never adds ``last-v1.ckpt``
    )
    on_signal = CheckpointOnSignal(output_dir / "checkpoints" / "last.ckpt",
                                   getattr(signal, cfg.trainer.slurm_requeue_signal, None))
    return L.Trainer(
        accelerator=cfg.trainer.accelerator,
        devices=cfg.trainer.devices,
        num_nodes=cfg.trainer.num_nodes,
        strategy=build_strategy(cfg.trainer),
        precision=cfg.trainer.precision,
        max_steps=cfg.stage.max_steps,
        max_epochs=-1,
        limit_val_batches=0,
        num_sanity_val_steps=0,
        log_every_n_steps=cfg.trainer.log_every_n_steps,
        logger=build_loggers(cfg, output_dir),
        callbacks=[checkpoints, on_signal, PlainTrainingProgress(), *weight_average(cfg.stage),
                   AttentionKernelCheck(cfg.backbone.transformer.require_fused_attention), *extra_callbacks],
        enable_progress_bar=cfg.trainer.enable_progress_bar and interactive(),  # else plain progress lines
        deterministic=cfg.trainer.deterministic,
        fast_dev_run=cfg.trainer.fast_dev_run,
        overfit_batches=cfg.trainer.overfit_batches,
        detect_anomaly=cfg.trainer.detect_anomaly,
        plugins=[SLURMEnvironment(requeue_signal=getattr(signal, cfg.trainer.slurm_requeue_signal))]
        if SLURMEnvironment.detect()
        else None,
        enable_model_summary=False,
        default_root_dir=output_dir,
    )


def resume_checkpoint(cfg: TrainConfig, output_dir: Path) -> str | None:
    """The checkpoint to resume from: an explicit path; for "last" the newer of this run's ``last.ckpt`` and the
    checkpoints of its SLURM requeues (None when it has neither); or None."""
    resume = cfg.stage.resume_from
    if resume is None:
        return None
    if resume == "last":
        # Lightning resumes from its requeue checkpoint (hpc_ckpt_<n>.ckpt) only when given no path, and this
        # run names last.ckpt once one exists. A job that SLURM kills after the requeue checkpoint and before
        # its next periodic save (SIGKILL at the end of KillWait, or a long step) leaves the requeue
        # checkpoint ahead of last.ckpt: resuming from last.ckpt would train those steps again.
        newest = newest_checkpoint([output_dir / "checkpoints" / "last.ckpt", *requeue_checkpoints(output_dir)],
                                   "stage.resume_from")
        keep_newest_requeue_checkpoint(output_dir)  # a job killed before it pruned left older ones
        return None if newest is None else str(newest)
    if not Path(resume).is_file():
        raise FileNotFoundError(f"stage.resume_from: no such checkpoint {resume}")
    require_loadable_checkpoint(resume, "stage.resume_from")
    return resume


def export_product(module: RestorerTrainingModule, stage: str, output_dir: Path,
                   lora_state: dict | None = None) -> Path:
    """Write the stage's product atomically into its folder (the stage table's) and return its path
    (``lora_state``: the adapters' whole weights when the transformer is sharded)."""
    product = output_dir / stage_table().stage(stage).folder
    module.export(product, lora_state)
    return product


def as_train_config(cfg) -> TrainConfig:
    """Accept a ``TrainConfig`` or a DictConfig of the same structure (validated against the schema)."""
    if isinstance(cfg, TrainConfig):
        return cfg
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(TrainConfig), cfg))
    raise TypeError(f"train_stage expects a TrainConfig or DictConfig, got {type(cfg).__name__}")


def train_stage(cfg) -> Path:
    """Train the stage named by ``cfg.stage.name`` (resuming if a checkpoint exists); return its product."""
    quiet_library_notices()  # the entry point of every stage, from the command line or from Python
    cfg = copy.deepcopy(as_train_config(cfg))
    require_trainer_device(cfg.trainer.accelerator)
    output_dir = Path(cfg.output_dir)
    require_writable_dir(output_dir / "checkpoints", "output_dir (run_dir)")
    resume = resume_checkpoint(cfg, output_dir)  # checked before any work
    trains = stage_module(cfg.stage.name)
    if cfg.trainer.strategy == "fsdp" and not trains.trains_adapters:
        raise ValueError(f"trainer.strategy: fsdp shards adapter training, and stage={cfg.stage.name} trains the "
                         f"whole transformer; train stage={cfg.stage.name} with trainer=ddp")
    if cfg.trainer.strategy == "fsdp" and cfg.stage.deployment_eval.scenes:
        raise ValueError("stage.deployment_eval: rank 0 deploys alone, which a sharded transformer cannot do "
                         "(train with trainer=ddp, or set stage.deployment_eval.scenes to [])")
    L.seed_everything(cfg.stage.seed, workers=True, verbose=False)  # the seed is in the run's config
    if trains.trains_adapters and cfg.stage.base_weights is not None:
        if not Path(cfg.stage.base_weights).is_dir():
            raise FileNotFoundError(
                f"stage.base_weights: no baseline restorer directory {cfg.stage.base_weights} "
                "(train stage=baseline first, or set it to null to use backbone.transformer.pretrained_path)"
            )
        cfg.backbone.transformer.pretrained_path = cfg.stage.base_weights
    if cfg.stage.batch_size is not None:
        cfg.data.batch_size = cfg.stage.batch_size
    backbone = build_backbone(cfg.backbone, encoders=False)  # the cache holds every encoder's output
    module = build_module(cfg, backbone)
    teacher = cfg.teacher.views if module.reads_teacher else NO_TEACHER
    datamodule = PairedClipDataModule(cfg.data, teacher_views=teacher)
    if cfg.trainer.strategy == "fsdp" and cfg.trainer.fsdp.activation_checkpointing:
        backbone.transformer.disable_gradient_checkpointing()  # FSDP checkpoints the blocks instead
    with one_job_of_processes():  # trainer.cpu_threads is set for every command (tracegs.cli.app.run_task)
        trainer = build_trainer(cfg, output_dir, module,
                                [*deployment_eval(cfg, backbone, module),
                                 *held_out_eval(cfg, backbone, module, output_dir)])
        finished = finished_checkpoint_state(resume, cfg.stage.max_steps) if resume else None
        if finished is not None:
            # Killed after its last checkpoint and before its export: export what that checkpoint holds.
            module.on_load_checkpoint(finished)
            module.load_state_dict(finished["state_dict"], strict=False)
        else:
            try:
                with sigterm_at_its_default():  # Lightning's own: a checkpoint after the step in flight
                    trainer.fit(module, datamodule=datamodule, ckpt_path=resume)
            except SIGTERMException:
                raise stopped_by_signal(output_dir / "checkpoints" / "last.ckpt", trainer.global_step) from None
        product = output_dir / stage_table().stage(cfg.stage.name).folder
        lora_state = full_lora_state(module.transformer)  # sharded adapters gathered on every rank (a collective)
        if trainer.is_global_zero:
            export_product(module, cfg.stage.name, output_dir, lora_state)
        trainer.strategy.barrier()
    return product
