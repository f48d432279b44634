"""Stage 2, on-policy trajectory distillation with privileged geometry (Sec. 3.4, Eqs. 4-9, Algorithm 1)."""

from __future__ import annotations

import contextlib

import torch
from lightning.pytorch.strategies import ParallelStrategy
from torch import Tensor, nn

from tracegs.restorer.adapters import activate, adapter_parameters, clone_adapter, load_adapter, save_adapter
from tracegs.restorer.config import LoraConfig
from tracegs.training.config import MEMORY_MODES, OptimizerConfig
from tracegs.training.losses import distillation_state_loss
from tracegs.training.module import RestorerTrainingModule, typed

TEACHER = "teacher"
STUDENT = "student"


class Stage2DistillationModule(RestorerTrainingModule):
    """Teacher = frozen clone, student = trainable clone of the Stage-1 adapter (Eq. supp-adapter-clone).

    Each step resamples an N-step grid from the M-step deployment schedule, rolls the student out from
    pure noise with detached transitions (Eq. 4), queries the frozen teacher at every visited state and
    timestep without a teacher rollout (Eq. 5), and minimises L_traj + lambda_ret L_ret (Eqs. 6, 8, 9).
    ``on_policy=False`` (variant E) evaluates the same objective at independently forward-noised
    pseudo-target states on the same grid.

    Memory modes give identical gradients: ``retain`` keeps the N student graphs until one backward of
    the averaged loss; ``stepwise`` back-propagates loss_i / N at each state, so only one student graph
    is alive at a time. This is exact because no gradient crosses a (detached) transition.
    """

    def __init__(
        self,
        transformer: nn.Module,
        schedule,
        init_adapter,
        optimizer: OptimizerConfig,
        rollout_steps: int = 5,
        deploy_steps: int = 20,
        lambda_ret: float = 0.15,
        retrieval_eps: float = 1e-6,
        on_policy: bool = True,
        memory_mode: str = "stepwise",
        seed: int = 0,
        lora: LoraConfig | None = None,
    ) -> None:
        super().__init__(transformer, schedule, optimizer, seed)
        if memory_mode not in MEMORY_MODES:
            raise ValueError(f"stage.memory_mode must be one of {MEMORY_MODES}, got {memory_mode!r}")
        if not 1 <= rollout_steps <= deploy_steps:
            raise ValueError(f"stage.rollout_steps must be in [1, M={deploy_steps}], got {rollout_steps}")
        self.rollout_steps = rollout_steps
        self.deploy_steps = deploy_steps
        self.lambda_ret = lambda_ret
        self.retrieval_eps = retrieval_eps
        self.on_policy = on_policy
        self.memory_mode = memory_mode
        self.transformer.requires_grad_(False)
        # The aligned adapter is loaded once and deep-copied: no re-initialisation, no shared tensors.
        # ``lora`` (the run's backbone.lora) must match the file: the student trains at the configured rank.
        load_adapter(self.transformer, STUDENT, init_adapter, trainable=True, expected=typed(lora, LoraConfig),
                     field="stage.init_adapter")
        clone_adapter(self.transformer, STUDENT, TEACHER, trainable=False)
        self._student_params = adapter_parameters(self.transformer, STUDENT)
        activate(self.transformer, STUDENT)

    def trainable_parameters(self) -> list[nn.Parameter]:
        return self._student_params

    def training_grid(self, generator: torch.Generator) -> Tensor:
        """{t'_i}_{i=0..N}, resampled from the M-step deployment schedule (Algorithm 1, line 4).

        Returned in rollout order: element 0 is pure noise (t'_N), the last element the clean end (t'_0).
        """
        return self.schedule.resample(self.schedule.timesteps(self.deploy_steps), self.rollout_steps, generator)

    def compute_and_backward(self, batch: dict, generator) -> dict[str, Tensor]:
        student_cond = self.latent(batch, "student_cond")
        teacher_cond = self.latent(batch, "teacher_cond")
        target = self.latent(batch, "target")
        grid = self.training_grid(generator)
        read_retrieval = self.lambda_ret != 0.0
        n = self.rollout_steps
        state = self.randn_like(target, generator)  # z_{t'_N} ~ N(0, I)
        retained: list[Tensor] = []
        totals: dict[str, Tensor] = {}
        for i in range(n):
            t, t_next = grid[i], grid[i + 1]
            if not self.on_policy:
                # Variant E: an independently forward-noised pseudo-target state at the same grid point.
                state = self.schedule.add_noise(target, self.randn_like(target, generator), t)
            activate(self.transformer, TEACHER)
            with torch.no_grad():
                teacher = self.predict(state, teacher_cond, t, batch, return_retrieval=read_retrieval)
            activate(self.transformer, STUDENT)
            student = self.predict(state, student_cond, t, batch, return_retrieval=read_retrieval)
            terms = distillation_state_loss(
                student.velocity,
                teacher.velocity,
                student.retrieval,
                teacher.retrieval,
                self.lambda_ret,
                self.retrieval_eps,
            )
            if self.memory_mode == "stepwise":
                # Under DDP only the last backward synchronises: the earlier ones accumulate locally.
                with self._gradient_sync(last=i == n - 1):
                    self.manual_backward(terms["loss"] / n)
            else:
                retained.append(terms["loss"])
            for name, value in terms.items():
                totals[name] = totals.get(name, 0.0) + value.detach() / n
            if self.on_policy:
                # Eq. 4: the transition uses the student's own velocity and is detached.
                state = self.schedule.step(state, student.velocity.detach(), t, t_next).detach()
        if retained:
            self.manual_backward(torch.stack(retained).mean())
        return totals

    def _gradient_sync(self, last: bool):
        """Context for one stepwise backward: DDP's all-reduce is deferred to the rollout's last backward."""
        strategy = self.trainer.strategy
        if last or not isinstance(strategy, ParallelStrategy):
            return contextlib.nullcontext()
        return strategy.block_backward_sync()

    def save_student(self, path) -> None:
        """Write the distilled student adapter phi_S (the only thing deployment needs)."""
        save_adapter(self.transformer, STUDENT, path)
