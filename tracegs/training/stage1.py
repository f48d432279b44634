"""Stage 1, privileged direction alignment (paper Sec. 3.3, supplement Eq. supp-stage1)."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from tracegs.products import STAGE1
from tracegs.restorer.adapters import activate, adapter_parameters, add_adapter, save_adapter
from tracegs.restorer.config import LoraConfig
from tracegs.training.config import OptimizerConfig, TrainConfig
from tracegs.training.losses import warm_loss
from tracegs.training.module import RestorerTrainingModule, typed


class Stage1AlignmentModule(RestorerTrainingModule):
    """One shared LoRA adapter phi trained on L_warm = L_fm^S + L_fm^T + lambda_align L_align.

    Both roles receive the same z_t (the pseudo-target latent forward-noised with one shared noise
    sample at one shared t) and differ only in their condition (R_s vs R_d). The teacher velocity v_T is
    recomputed by the current adapter at every step (online target) and detached inside L_align only.
    The adapter is attached fresh (B = 0), so at step 0 the model equals the base restorer (variant A).
    """

    def __init__(
        self,
        transformer: nn.Module,
        schedule,
        lora_cfg,
        optimizer: OptimizerConfig,
        lambda_align: float = 1.0,
        adapter_name: str = "aligned",
        seed: int = 0,
    ) -> None:
        super().__init__(transformer, schedule, optimizer, seed)
        self.adapter_name = adapter_name
        self.lambda_align = lambda_align
        self.transformer.requires_grad_(False)
        lora_cfg = typed(lora_cfg, LoraConfig)
        add_adapter(self.transformer, adapter_name, lora_cfg)
        activate(self.transformer, adapter_name)

    def trainable_parameters(self) -> list[nn.Parameter]:
        return adapter_parameters(self.transformer, self.adapter_name)  # looked up: sharding replaces them

    def compute_and_backward(self, batch: dict, generator) -> dict[str, Tensor]:
        target = self.latent(batch, "target")
        batch_size = target.shape[0]
        noise = self.randn_like(target, generator)
        t = self.schedule.sample_train_t(batch_size, generator).to(self.device)
        noisy = self.schedule.add_noise(target, noise, t)
        # Both roles in one forward of a doubled batch: same z_t and t, conditions R_s then R_d.
        both = {key: torch.cat([batch[key], batch[key]]) for key in ("text", "ref_2d", "ref_3d")}
        cond = torch.cat([self.latent(batch, "student_cond"), self.latent(batch, "teacher_cond")])
        velocity = self.predict(torch.cat([noisy, noisy]), cond, torch.cat([t, t]), both).velocity
        v_student, v_teacher = velocity.split(batch_size)
        terms = warm_loss(v_student, v_teacher, self.schedule.velocity_target(target, noise, t), self.lambda_align,
                          self.fm_weight(t))
        self.manual_backward(terms["loss"])
        return {name: value.detach() for name, value in terms.items()}

    @classmethod
    def of(cls, cfg: TrainConfig, backbone) -> Stage1AlignmentModule:
        return cls(backbone.transformer, backbone.schedule, cfg.backbone.lora, cfg.optimizer,
                   lambda_align=cfg.loss.lambda_align, adapter_name=cfg.stage.adapter_name, seed=cfg.stage.seed)

    def export(self, path: Path, lora_state: dict | None = None) -> None:
        """Write the aligned adapter phi (safetensors) that Stage 2 clones into teacher and student."""
        save_adapter(self.transformer, self.adapter_name, path, lora_state, stage=STAGE1.value)

    @property
    def deployed_adapter(self) -> str:
        return self.adapter_name
