"""Variant A at the embedded scale: train the restorer on (R_s -> pseudo-target) pairs.

At paper scale variant A is GSFixer's pretrained restorer, loaded, and this module is not used. At the
embedded scale nobody ships a pretrained tiny restorer, so this module produces one with GSFixer's plain
denoising objective: flow-matching supervision at independently forward-noised states.

Design decision: the module trains the *full* tiny transformer (including the reference projections),
not a LoRA. Its weights then play the role the frozen pretrained backbone plays in the paper: Stage 1
loads them as the frozen base (``backbone.transformer.pretrained_path``) and attaches a fresh zero-init
adapter, so before Stage 1 the model equals variant A exactly (supplement A.3, "Low-rank update").
"""

from __future__ import annotations

from pathlib import Path

from torch import Tensor, nn

from tracegs.io import atomic_directory
from tracegs.training.config import OptimizerConfig, TrainConfig
from tracegs.training.losses import flow_matching_loss
from tracegs.training.module import RestorerTrainingModule


class BaselineRestorerModule(RestorerTrainingModule):
    """Trains every transformer weight with L_fm on the student-conditioned (sparse) rendering."""

    # The whole transformer, on R_s and its target only: its own pretraining scenes fit no teacher.
    trains_adapters = False
    reads_teacher = False

    def __init__(self, transformer: nn.Module, schedule, optimizer: OptimizerConfig, seed: int = 0) -> None:
        super().__init__(transformer, schedule, optimizer, seed)
        self.transformer.requires_grad_(True)

    @classmethod
    def of(cls, cfg: TrainConfig, backbone) -> BaselineRestorerModule:
        return cls(backbone.transformer, backbone.schedule, cfg.optimizer, seed=cfg.stage.seed)

    def export(self, path: Path, lora_state: dict | None = None) -> None:
        """A diffusers directory of the whole transformer: several files, so the directory is the atomic unit."""
        with atomic_directory(path) as staging:
            self.transformer.save_pretrained(staging)

    @property
    def deployed_adapter(self) -> None:
        return None

    def trainable_parameters(self) -> list[nn.Parameter]:
        return list(self.transformer.parameters())

    def compute_and_backward(self, batch: dict, generator) -> dict[str, Tensor]:
        target = self.latent(batch, "target")
        noise = self.randn_like(target, generator)
        t = self.schedule.sample_train_t(target.shape[0], generator).to(self.device)
        noisy = self.schedule.add_noise(target, noise, t)
        velocity = self.predict(noisy, self.latent(batch, "student_cond"), t, batch).velocity
        loss = flow_matching_loss(velocity, self.schedule.velocity_target(target, noise, t), self.fm_weight(t))
        self.manual_backward(loss)
        return {"loss": loss.detach(), "fm_student": loss.detach()}
