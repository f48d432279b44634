"""Stage 2, on-policy trajectory distillation with privileged geometry (Sec. 3.4, Eqs. 4-9, Algorithm 1)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import torch
from lightning.pytorch.strategies import ParallelStrategy
from torch import Tensor, nn

from tracegs.products import STAGE1, STAGE2
from tracegs.restorer.adapters import activate, adapter_parameters, clone_adapter, load_adapter, save_adapter
from tracegs.restorer.config import LoraConfig
from tracegs.restorer.sampler import first_state, guided_prediction, initial_noise, solve
from tracegs.training.config import (
    MemoryMode,
    OptimizerConfig,
    TrainConfig,
    TrajectorySpace,
    TrajectoryTarget,
)
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

    The rollout is the deployment sampler's solver (``sampler.solve``) with the same initial-noise draw and
    sampling temperature (``backbone.sampler.temperature``).
    ``guidance_scale`` (``stage.guidance_scale``) is 1 by default: the student advances with its own
    conditional velocity u_i = v(z_{t'_i}, t'_i, R_s) and the teacher is queried once per state, N student
    forwards with gradient and N teacher forwards without, as the supplement writes Eqs. 4-6. Any other scale
    queries both roles under classifier-free guidance (the unconditional branch with the all-zero text
    embedding), doubling every evaluation and the student's activations; deployment's own guidance
    (``backbone.sampler.guidance_scale``) is separate.

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
        memory_mode: MemoryMode | str = MemoryMode.stepwise,
        seed: int = 0,
        lora: LoraConfig | None = None,
        guidance_scale: float = 1.0,
        temperature: float = 1.0,
        trajectory_space: TrajectorySpace | str = TrajectorySpace.velocity,
        trajectory_target: TrajectoryTarget | str = TrajectoryTarget.teacher,
    ) -> None:
        super().__init__(transformer, schedule, optimizer, seed)
        if not 1 <= rollout_steps <= deploy_steps:
            raise ValueError(f"stage.rollout_steps must be in [1, M={deploy_steps}], got {rollout_steps}")
        self.rollout_steps = rollout_steps
        self.deploy_steps = deploy_steps
        self.lambda_ret = lambda_ret
        self.retrieval_eps = retrieval_eps
        self.on_policy = on_policy
        self.memory_mode = MemoryMode.parse(memory_mode, "stage.memory_mode")
        self.guidance_scale = guidance_scale
        self.temperature = temperature
        self.trajectory_space = TrajectorySpace.parse(trajectory_space, "loss.trajectory_space")
        self.trajectory_target = TrajectoryTarget.parse(trajectory_target, "loss.trajectory_target")
        self.transformer.requires_grad_(False)
        # The aligned adapter is loaded once and deep-copied: no re-initialisation, no shared tensors.
        # ``lora`` (the run's backbone.lora) must match the file: the student trains at the configured rank.
        load_adapter(self.transformer, STUDENT, init_adapter, trainable=True, expected=typed(lora, LoraConfig),
                     field="stage.init_adapter", stage=STAGE1.value)
        clone_adapter(self.transformer, STUDENT, TEACHER, trainable=False)
        activate(self.transformer, STUDENT)

    def trainable_parameters(self) -> list[nn.Parameter]:
        return adapter_parameters(self.transformer, STUDENT)  # looked up: sharding replaces them

    def training_grid(self, generator: torch.Generator) -> Tensor:
        """{t'_i}_{i=0..N}, resampled from the M-step deployment schedule (Algorithm 1, line 4).

        Returned in rollout order: element 0 is pure noise (t'_N), the last element the clean end (t'_0).
        """
        return self.schedule.resample(self.schedule.timesteps(self.deploy_steps), self.rollout_steps, generator)

    def compute_and_backward(self, batch: dict, generator) -> dict[str, Tensor]:
        grid = self.training_grid(generator)
        n = self.rollout_steps
        retained: list[Tensor] = []
        totals: dict[str, Tensor] = {}

        def supervise(i: int, state: Tensor, t: Tensor) -> Tensor:
            """Eqs. 5-9 at one visited state; returns the student's velocity, which drives the transition."""
            terms, student_velocity = self.state_loss(batch, state, t)
            if self.memory_mode is MemoryMode.stepwise:
                # Under DDP only the last backward synchronises: the earlier ones accumulate locally.
                with self._gradient_sync(last=i == n - 1):
                    self.manual_backward(terms["loss"] / n)
            else:
                retained.append(terms["loss"])
            for name, value in terms.items():
                totals[name] = totals.get(name, 0.0) + value.detach() / n
            return student_velocity

        if self.on_policy:
            self.rollout(batch, grid, generator, supervise)
        else:
            target = self.latent(batch, "target")
            # Draw (and leave unused) the rollout's initial noise so the generator stream of variant E stays
            # the one it has always had: its forward-noising draws follow the grid and that draw.
            initial_noise(target.shape, generator, target.device)
            for i in range(n):
                # Variant E: an independently forward-noised pseudo-target state at the same grid point.
                t = grid[i].expand(target.shape[0]).to(target.device)
                supervise(i, self.schedule.add_noise(target, self.randn_like(target, generator), t), t)
        if retained:
            self.manual_backward(torch.stack(retained).mean())
        return totals

    def rollout(self, batch: dict, grid: Tensor, generator: torch.Generator, velocity=None) -> list[Tensor]:
        """The student's on-policy rollout (Eq. 4) on ``grid`` from noise drawn from ``generator``: the
        deployment solver (``sampler.solve``) with the student's velocity under ``guidance_scale``, so the
        visited states are the deployment sampler's for the same noise, grid, guidance and adapter.
        ``velocity(i, z, t)`` replaces the plain student velocity (training supervises each state there);
        returns every state."""
        activate(self.transformer, STUDENT)
        student_cond = self.latent(batch, "student_cond")
        noise = first_state(self.schedule, initial_noise(student_cond.shape, generator, student_cond.device),
                            self.temperature)
        if velocity is None:
            def velocity(_: int, state: Tensor, t: Tensor) -> Tensor:
                return self.guided(state, student_cond, t, batch).velocity
        return solve(self.schedule, grid, noise, velocity, keep_states=True)

    def state_loss(self, batch: dict, state: Tensor, t: Tensor) -> tuple[dict[str, Tensor], Tensor]:
        """The teacher (no gradient) and the student queried at one state under the same guidance rule
        (Eq. 5); returns the loss terms of Eqs. 6, 8, 9 and the student's velocity."""
        read_retrieval = self.lambda_ret != 0.0
        activate(self.transformer, TEACHER)
        with torch.no_grad():
            teacher = self.guided(state, self.latent(batch, "teacher_cond"), t, batch, read_retrieval)
        activate(self.transformer, STUDENT)
        student = self.guided(state, self.latent(batch, "student_cond"), t, batch, read_retrieval)
        target_velocity = teacher.velocity
        if self.trajectory_target is TrajectoryTarget.pseudo_target:
            target_velocity = self.schedule.velocity_toward(state, self.latent(batch, "target"), t.to(state.device))
        compared = (student.velocity, target_velocity)
        if self.trajectory_space is TrajectorySpace.clean:
            compared = tuple(self.schedule.predict_clean(state, v, t.to(state.device)) for v in compared)
        terms = distillation_state_loss(
            *compared,
            student.retrieval,
            teacher.retrieval,
            self.lambda_ret,
            self.retrieval_eps,
        )
        return terms, student.velocity

    def guided(self, state: Tensor, cond: Tensor, t: Tensor, batch: dict, return_retrieval: bool = False):
        """The active adapter's prediction under ``guidance_scale`` (1: the plain conditional velocity)."""
        return guided_prediction(self.transformer, state, cond, t.to(state.device), self._float(batch["text"]),
                                 self._float(batch["ref_2d"]), self._float(batch["ref_3d"]), self.guidance_scale,
                                 return_retrieval=return_retrieval)

    def _gradient_sync(self, last: bool):
        """Context for one stepwise backward: DDP's all-reduce is deferred to the rollout's last backward."""
        strategy = self.trainer.strategy
        if last or not isinstance(strategy, ParallelStrategy):
            return contextlib.nullcontext()
        return strategy.block_backward_sync()

    @classmethod
    def of(cls, cfg: TrainConfig, backbone) -> Stage2DistillationModule:
        stage = cfg.stage
        if stage.init_adapter is None:
            raise ValueError("stage.init_adapter must name the Stage-1 adapter for stage2")
        if not Path(stage.init_adapter).exists():
            raise FileNotFoundError(f"stage.init_adapter: no such file {stage.init_adapter}")
        return cls(
            backbone.transformer,
            backbone.schedule,
            stage.init_adapter,
            cfg.optimizer,
            rollout_steps=stage.rollout_steps,
            deploy_steps=cfg.backbone.schedule.deploy_steps,
            lambda_ret=cfg.loss.lambda_ret,
            retrieval_eps=cfg.loss.retrieval_eps,
            trajectory_space=cfg.loss.trajectory_space,
            trajectory_target=cfg.loss.trajectory_target,
            on_policy=cfg.policy.on_policy,
            memory_mode=stage.memory_mode,
            seed=stage.seed,
            lora=cfg.backbone.lora,
            guidance_scale=stage.guidance_scale,
            temperature=cfg.backbone.sampler.temperature,
        )

    def export(self, path: Path, lora_state: dict | None = None) -> None:
        """Write the distilled student adapter phi_S (the only thing deployment needs)."""
        save_adapter(self.transformer, STUDENT, path, lora_state, stage=STAGE2.value)

    @property
    def deployed_adapter(self) -> str:
        return STUDENT
