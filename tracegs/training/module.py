"""Shared LightningModule machinery for the three training stages.

All stages use Lightning's manual optimisation so that Stage 2 can back-propagate each visited state's
loss as soon as it is computed (``stepwise`` memory mode) while every stage shares one optimiser step
(AdamW, linear warm-up, optional global-norm clipping) and one set of logged quantities.

Randomness (timesteps, noise, resampled grids) comes from a generator seeded by (seed, rank, global
step) rather than from the global RNG, so a run resumed from a checkpoint draws exactly what the
uninterrupted run would have drawn at the same step.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from abc import abstractmethod
from enum import Enum
from pathlib import Path, PurePath

import lightning as L
import torch
from torch import Tensor, nn

from tracegs.errors import ConfigMismatchError, NonFiniteError
from tracegs.restorer.config import LossWeighting
from tracegs.training.config import OptimizerConfig, TrainConfig
from tracegs.training.strategy import ShardedRestorerStrategy

# Checkpoint entry holding the restorer's diffusers config, compared on resume.
MODEL_CONFIG_KEY = "tracegs_transformer_config"

# Large odd multipliers keep the (seed, rank, step) -> generator-seed map collision-free in practice.
_RANK_STRIDE = 1_000_003
_SEED_STRIDE = 7_919_000_017


def typed(value, cls):
    """A config dataclass from itself or from the plain dict a checkpoint's hyperparameters hold."""
    return value if value is None or isinstance(value, cls) else cls(**value)


def _plain(value):
    """A constructor argument as a type ``torch.load(weights_only=True)`` accepts (a config mode, an Enum,
    as its value)."""
    if dataclasses.is_dataclass(value):
        return _plain(dataclasses.asdict(value))
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_plain(item) for item in value)
    if isinstance(value, Enum):
        return value.value
    return str(value) if isinstance(value, PurePath) else value


def lr_factor(step: int, warmup_steps: int, decay: str = "constant", total_steps: int | None = None) -> float:
    """Learning-rate multiplier: linear warm-up, (step + 1) / warmup_steps for the first ``warmup_steps``
    steps, then 1 ("constant", the paper's Stage 2) or a cosine from 1 to 0 at ``total_steps`` ("cosine")."""
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    if decay == "constant" or total_steps is None or total_steps <= warmup_steps:
        return 1.0
    progress = min(1.0, (step - warmup_steps) / (total_steps - warmup_steps))
    return 0.5 * (1.0 + math.cos(math.pi * progress))


class RestorerTrainingModule(L.LightningModule):
    """Base class: owns the transformer and schedule, the optimiser step and the logging.

    Subclasses implement ``trainable_parameters`` and ``compute_and_backward`` (which must call
    ``self.manual_backward`` on its losses and return the detached terms to log), and for the runner
    (tracegs.training.run, which finds a stage's subclass in the stage table, tracegs.stages) ``of``, ``export``
    and ``deployed_adapter``, and the class attributes ``trains_adapters`` and ``reads_teacher``.
    Checkpoints contain only the trainable parameters (at paper scale the frozen 5B backbone would
    otherwise be copied into every checkpoint); everything frozen is rebuilt from the configuration.
    """

    # Whether the stage trains adapters on frozen base weights (``stage.base_weights``; FSDP shards adapter
    # training only), and whether its clips carry the privileged teacher conditions (``teacher.views``).
    trains_adapters: bool = True
    reads_teacher: bool = True

    def __init__(self, transformer: nn.Module, schedule, optimizer: OptimizerConfig, seed: int) -> None:
        super().__init__()
        self.automatic_optimization = False
        # Checkpoints hold only trainable weights; ``on_load_checkpoint`` checks the key set itself.
        self.strict_loading = False
        # build_backbone returns the restorer in eval mode; Lightning keeps submodule modes, so switch here
        # (train mode is what enables diffusers' gradient checkpointing at paper scale).
        self.transformer = transformer.train()
        self.schedule = schedule
        self.optimizer_cfg = typed(optimizer, OptimizerConfig)
        self.seed = seed
        self._save_plain_hyperparameters()

    def _save_plain_hyperparameters(self) -> None:
        """Record the constructor arguments of the whole class chain, as plain types, in every checkpoint.

        ``load_from_checkpoint(path, transformer=..., schedule=...)`` then rebuilds the module around a
        restorer built from its config (frozen weights are never in a checkpoint); plain types keep the
        checkpoint loadable with ``weights_only=True``.
        """
        self.save_hyperparameters(ignore=["transformer", "schedule"])
        plain = {key: _plain(value) for key, value in self.hparams.items()}
        self.hparams.clear()
        self.hparams.update(plain)
        self._hparams_initial = copy.deepcopy(self._hparams)

    # ----------------------------------------------------------------- subclass interface
    def _apply(self, fn, recurse=True):
        """``module.to(...)`` and friends, except that trainable parameters keep float32.

        Lightning's ``bf16-true`` / ``16-true`` plugins convert the whole module to half precision before the
        optimiser is built; trainable adapter factors (and so AdamW's state) must stay float32 there too, or lr
        1e-5 updates round away (see ``tracegs.restorer.adapters``). The float32 values are kept exactly, not
        rounded through half precision and back; only a device move applies to them.
        """
        trainable = self._trainable_if_built()
        kept = {id(p): p.data for p in trainable if p.dtype == torch.float32}
        result = super()._apply(fn, recurse)
        for param in trainable:
            if id(param) in kept and param.dtype != torch.float32:
                param.data = kept[id(param)].to(param.device)
        return result

    def _trainable_if_built(self) -> list[nn.Parameter]:
        # ``_apply`` may run before a subclass's ``__init__`` has added its adapter.
        try:
            return self.trainable_parameters()
        except (AttributeError, KeyError):
            return []

    @abstractmethod
    def trainable_parameters(self) -> list[nn.Parameter]:
        """The parameters the optimiser updates (and the only ones saved in checkpoints)."""

    @abstractmethod
    def compute_and_backward(self, batch: dict, generator: torch.Generator) -> dict[str, Tensor]:
        """Compute this stage's losses for ``batch``, back-propagate them, return detached terms to log."""

    @classmethod
    @abstractmethod
    def of(cls, cfg: TrainConfig, backbone) -> RestorerTrainingModule:
        """The module of a ``cfg.stage.name`` run around the backbone's transformer and schedule."""

    @abstractmethod
    def export(self, path: Path, lora_state: dict | None = None) -> None:
        """Write the stage's product to ``path`` atomically (``lora_state``: the adapters' whole weights when the
        transformer is sharded)."""

    @property
    @abstractmethod
    def deployed_adapter(self) -> str | None:
        """The adapter the stage's restorer deploys with (None: the transformer alone)."""

    # ----------------------------------------------------------------- helpers for subclasses
    def predict(self, noisy: Tensor, cond: Tensor, timestep: Tensor, batch: dict, return_retrieval: bool = False):
        """One restorer evaluation v(z_t, t, cond) with the sample's reference tokens and text embedding."""
        if timestep.ndim == 0:
            timestep = timestep.expand(noisy.shape[0])
        return self.transformer(
            noisy,
            cond,
            timestep.to(noisy.device),
            self._float(batch["text"]),
            self._float(batch["ref_2d"]),
            self._float(batch["ref_3d"]),
            return_retrieval=return_retrieval,
        )

    def fm_weight(self, t: Tensor) -> Tensor | None:
        """Per-sample weight of L_fm at training times ``t``: EDM's for a preconditioned restorer with
        ``schedule.train_loss_weighting=edm`` (``Preconditioning.loss_weight``), else None (the plain L_fm)."""
        return self.transformer.loss_weight(t) if self.schedule.cfg.train_loss_weighting == LossWeighting.edm else None

    def latent(self, batch: dict, key: str) -> Tensor:
        """A latent tensor of the batch in the training dtype (the cache may store float16)."""
        return self._float(batch[key])

    def randn_like(self, reference: Tensor, generator: torch.Generator) -> Tensor:
        """Gaussian noise drawn on the CPU generator (device-independent streams), moved to the device."""
        noise = torch.randn(reference.shape, generator=generator, dtype=torch.float32)
        return noise.to(device=reference.device, dtype=reference.dtype)

    def _float(self, tensor: Tensor) -> Tensor:
        return tensor.to(device=self.device, dtype=torch.float32) if tensor.is_floating_point() else tensor

    def step_generator(self) -> torch.Generator:
        """Generator for this optimiser step, a pure function of (seed, rank, global step)."""
        seed = self.seed * _SEED_STRIDE + self.global_rank * _RANK_STRIDE + self.global_step
        return torch.Generator().manual_seed(seed % (2**63 - 1))

    # ----------------------------------------------------------------- Lightning hooks
    def configure_model(self) -> None:
        """Lightning's parallelisation hook: a sharding strategy (``trainer.strategy: fsdp``) shards the restorer
        here, after the processes have started and before the optimiser is built; other strategies, and
        ``load_from_checkpoint`` (no Trainer, hence ``_trainer``), leave it."""
        strategy = getattr(self._trainer, "strategy", None)
        if isinstance(strategy, ShardedRestorerStrategy):
            strategy.shard(self.transformer)

    def configure_optimizers(self):
        cfg = self.optimizer_cfg
        # The cosine ends at the Trainer's max_steps; without a Trainer (or a step budget) the rate stays
        # constant after warm-up. ``_trainer`` because the public property raises when none is attached.
        trainer = self._trainer
        total_steps = trainer.max_steps if trainer is not None and trainer.max_steps > 0 else None
        optimizer = torch.optim.AdamW(
            self.trainable_parameters(),
            lr=cfg.lr,
            betas=tuple(cfg.betas),
            eps=cfg.eps,
            weight_decay=cfg.weight_decay,
        )
        scheduler = torch.optim.lr_scheduler.LambdaLR(
            optimizer, lambda step: lr_factor(step, cfg.warmup_steps, cfg.decay, total_steps)
        )
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def training_step(self, batch: dict, batch_idx: int) -> None:
        optimizer = self.optimizers()
        scheduler = self.lr_schedulers()
        started = time.perf_counter()
        lr = optimizer.param_groups[0]["lr"]
        optimizer.zero_grad(set_to_none=True)
        terms = self.compute_and_backward(batch, self.step_generator())
        grads = [p.grad for p in self.trainable_parameters() if p.grad is not None]
        grad_norm = torch.nn.utils.get_total_norm(grads) if grads else torch.zeros(())
        self.stop_if_non_finite(batch, terms["loss"], grad_norm)
        if self.optimizer_cfg.grad_clip is not None:
            self.clip_gradients(
                optimizer, gradient_clip_val=self.optimizer_cfg.grad_clip, gradient_clip_algorithm="norm"
            )
        optimizer.step()
        scheduler.step()
        elapsed = time.perf_counter() - started
        batch_size = batch["target"].shape[0]
        logged = {f"train/{name}": value for name, value in terms.items()}
        logged["train/grad_norm"] = grad_norm
        logged["train/lr"] = lr
        logged["train/samples_per_sec"] = batch_size / max(elapsed, 1e-9)
        logged["train/step_time_s"] = elapsed
        self.log_dict(logged, prog_bar=False, batch_size=batch_size, on_step=True, on_epoch=False)
        self.log("loss", terms["loss"], prog_bar=True, batch_size=batch_size, on_step=True, on_epoch=False)

    def stop_if_non_finite(self, batch: dict, loss: Tensor, grad_norm: Tensor) -> None:
        """Stop before the optimiser step when the loss or gradient norm is NaN or infinite.

        One bad batch would otherwise turn every weight into NaN while the run carries on and exits 0. The
        weights are still those of the last good step, and no checkpoint is written on the way out.
        """
        if bool(torch.isfinite(loss)) and bool(torch.isfinite(grad_norm)):
            return
        clips = [f"{scene}/clip_{int(clip):03d}" for scene, clip in zip(batch["scene"], batch["clip"])]
        raise NonFiniteError(
            f"step {self.global_step}",
            f"non-finite loss ({float(loss):.4g}) or gradient norm ({float(grad_norm):.4g}) on clips "
            f"{', '.join(clips)}",
            "check those cache shards (re-run tracegs-prepare) or the learning rate; rerunning resumes from "
            "the last good checkpoint",
        )

    def _trainable_names(self) -> set[str]:
        ids = {id(p) for p in self.trainable_parameters()}
        return {name for name, p in self.named_parameters() if id(p) in ids}

    def _model_config(self) -> dict:
        # Plain values: config modes are Enums, which a weights_only checkpoint load refuses.
        return {k: _plain(v) for k, v in self.transformer.config.items() if not k.startswith("_")}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        keep = self._trainable_names()
        checkpoint["state_dict"] = {k: v for k, v in checkpoint["state_dict"].items() if k in keep}
        checkpoint[MODEL_CONFIG_KEY] = self._model_config()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        # Same weight names do not mean the same model: e.g. a velocity head resumed as a residual head.
        stored, current = checkpoint.get(MODEL_CONFIG_KEY, {}), self._model_config()
        differing = {k: (v, current[k]) for k, v in stored.items() if k in current and current[k] != v}
        if differing:
            raise ValueError(f"checkpoint was written by another restorer configuration (stored, now): {differing}")
        expected, found = self._trainable_names(), set(checkpoint["state_dict"])
        if expected != found:
            missing, unexpected = sorted(expected - found)[:5], sorted(found - expected)[:5]
            raise ValueError(
                f"checkpoint does not match this stage's trainable weights: missing {missing}, "
                f"unexpected {unexpected}"
            )
        # Same names, other shapes: e.g. LoRA factors of another rank (Lightning would fail on a size mismatch).
        shapes = {name: tuple(p.shape) for name, p in self.named_parameters() if name in expected}
        resized = {k: (tuple(v.shape), shapes[k]) for k, v in checkpoint["state_dict"].items()
                   if tuple(v.shape) != shapes[k]}
        if resized:
            name, (stored_shape, shape) = next(iter(sorted(resized.items())))
            raise ConfigMismatchError(
                "stage.resume_from", f"the checkpoint's weights have other shapes than this run's ({len(resized)} "
                f"tensors, e.g. {name}: {stored_shape} in the checkpoint, {shape} now; was backbone.lora.rank "
                "changed?)", "resume with the settings the checkpoint was written with, or delete the run's "
                "checkpoints/ to start over")
