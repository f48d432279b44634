"""Hyperparameters of the three training stages (defaults = embedded CPU scale).

Paper-scale values (supplement A.4): AdamW lr 1e-5, batch 2 per GPU, lambda_align 1, lambda_ret 0.15,
N = 10 rollout steps resampled from the M = 50 deployment schedule, Stage 1 500 iterations, Stage 2 2000
iterations with 100 linear warm-up iterations. The baseline restorer (variant A) is GSFixer's pretrained
restorer at paper scale, so ``BaselineStage`` is only trained at the embedded scale.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tracegs.data.config import DataModuleConfig, SceneSourceConfig
from tracegs.deploy.config import CAPTURED_VIEWS, RefinementConfig
from tracegs.modes import Mode
from tracegs.products import BASELINE, STAGE1, STAGE2, execution, handed_in, reads, via
from tracegs.ranges import SEED, at_least, check_ranges, each, positive, within
from tracegs.restorer.config import BackboneConfig
from tracegs.splat.config import GaussianFitConfig
from tracegs.stages import StageName


class MemoryMode(Mode):
    """How Stage 2 back-propagates its N local losses (``StageConfig``)."""

    stepwise = "stepwise"
    retain = "retain"


class TrajectorySpace(Mode):
    """Where Stage 2 compares the student with the teacher at each visited state (``LossConfig``)."""

    velocity = "velocity"  # ||u_S - u_T||^2, main paper Eq. 6
    # ||x0_S - x0_T||^2 of the clean predictions the two velocities imply at the state: Eq. 6 with each state's
    # term weighted by t^2 (rectified flow), so the nearly clean states do not dominate the average.
    clean = "clean"


class TrajectoryTarget(Mode):
    """What the student is compared with at each visited state (``LossConfig``)."""

    teacher = "teacher"  # the frozen privileged teacher's prediction there, main paper Eq. 5
    # The velocity that would take the state to the clip's pseudo-target (supp. A.4). At the embedded scale the
    # pseudo-target is the ground truth, so this is an oracle teacher: it separates what the privileged teacher's
    # targets do from what supervising the student at its own states does.
    pseudo_target = "pseudo_target"


class LrDecay(Mode):
    """The learning rate after warm-up (``OptimizerConfig``)."""

    constant = "constant"  # supplement A.4
    cosine = "cosine"  # to zero at the stage's max_steps


@dataclass
class OptimizerConfig:
    """AdamW with linear warm-up (supplement A.4: the first 100 Stage-2 iterations warm up).

    The paper states AdamW, lr 1e-5 and the warm-up only; ``weight_decay``, ``betas``, ``eps`` and
    ``grad_clip`` are not stated in the paper, and each says below why its value was chosen.
    """

    lr: float = reads(BASELINE, default=1e-3, range=positive())
    # Not stated in the paper; 0 because decay would pull the LoRA factors towards zero, i.e. the student
    # towards the bare base and away from the Stage-1 adapter it is cloned from, which no loss asks for.
    weight_decay: float = reads(BASELINE, default=0.0, range=at_least(0))
    # Not stated in the paper; torch's AdamW defaults, as the paper names no departure from them.
    betas: list[float] = reads(BASELINE, factory=lambda: [0.9, 0.999],
                               range=each(within(0, 1, high_open=True)))
    eps: float = reads(BASELINE, default=1e-8, range=positive())  # not stated in the paper; torch's default
    warmup_steps: int = reads(BASELINE, default=0, range=at_least(0))
    # After warm-up: "constant" (supplement A.4) or "cosine" to zero at the stage's max_steps.
    decay: LrDecay = reads(BASELINE, default=LrDecay.constant)
    # Max global L2 norm of the trainable gradients; None disables clipping. Not stated in the paper; 1.0
    # (diffusers' fine-tuning scripts' max_grad_norm) bounds the step a rare outlier batch can take.
    grad_clip: float | None = reads(BASELINE, default=1.0, range=positive())

    def __post_init__(self) -> None:
        self.decay = LrDecay.parse(self.decay, "optimizer.decay")


@dataclass
class DeploymentEvalConfig:
    """Restore-refine deployment (Algorithm 1, bottom) of validation scenes with the restorer being trained, its
    PSNR/SSIM(/LPIPS) logged to the stage's loggers at the stage's end and every ``every_n_steps`` steps, so a
    sweep's variants can be compared while they train (tracegs/eval/callback.py). Off by default: no scene."""

    # Validation scenes to deploy on (synthetic benchmark: its val split's scene names); empty = off.
    scenes: list[str] = execution(factory=list)
    # sparse view counts K deployed from
    views: list[int] = execution(factory=lambda: [3], range=each(CAPTURED_VIEWS, non_empty=False))
    # also deploy every n optimizer steps (None: only at the end)
    every_n_steps: int | None = execution(default=None, range=at_least(1))
    lpips: bool = execution(default=False)  # LPIPS needs the VGG16 weights; PSNR and SSIM need nothing

    def __post_init__(self) -> None:
        check_ranges(self, "stage.deployment_eval")
        if self.scenes and not self.views:
            raise ValueError("stage.deployment_eval.views is empty: name the view counts K to deploy from")


@dataclass
class HeldOutEvalConfig:
    """The trained adapter's restoration of held-out clips, scored before the first step (with variant A beside
    it), every ``every_n_steps`` steps and at the end: the stage's learning curve, ``held_out_curve.{json,png}``
    in the run folder (tracegs/eval/held_out_curve.py). Off by default: no cache."""

    # A prepared held-out cache, e.g. the validation scenes' (tracegs-prepare data.prepare.split=val); None = off.
    cache: str | None = execution(default=None)
    every_n_steps: int = execution(default=25, range=at_least(1))

    def __post_init__(self) -> None:
        check_ranges(self, "stage.held_out_eval")


@dataclass
class StageConfig:
    """Which stage runs and its loop-level settings.

    ``rollout_steps`` is Stage 2's N (grid resampled each iteration from the M-step deployment schedule
    set by the backbone's schedule config). ``memory_mode`` chooses how Stage 2 back-propagates the N
    local losses: ``retain`` keeps all N student graphs until one backward (the paper's description),
    ``stepwise`` back-propagates each local loss divided by N right away (same gradients because the
    transitions are detached, memory independent of N).
    """

    name: StageName = reads(BASELINE, default=StageName.stage2)
    # 0: no step (variant A loaded, never trained: experiment.baseline_steps); never -1, which Lightning reads as
    # no limit.
    max_steps: int = reads(BASELINE, default=150, range=at_least(0))
    # Per-device batch size of this stage; None = data.batch_size.
    batch_size: int | None = reads(BASELINE, default=None, range=at_least(1))
    rollout_steps: int = reads(STAGE2, default=5, range=at_least(1))
    memory_mode: MemoryMode = reads(STAGE2, default=MemoryMode.stepwise)
    # Stage 2: classifier-free guidance of the rollout and of both roles' queries in the losses. 1 = none, as the
    # supplement writes the rollout (u_i = v(z_{t'_i}, t'_i, R_s), N student + N teacher forwards); any other
    # value adds an unconditional forward per query (the all-zero text) and doubles the student's activations.
    guidance_scale: float = reads(STAGE2, default=1.0, range=at_least(0))
    seed: int = reads(BASELINE, default=0, range=SEED)
    # Name of the LoRA adapter trained by Stage 1 and cloned into teacher/student by Stage 2.
    adapter_name: str = reads(BASELINE, default="aligned")
    # Stage 1 / 2: variant A's transformer (diffusers directory written by the baseline stage), used as the
    # frozen base; None = backbone.transformer.pretrained_path as configured (paper scale: GSFixer).
    base_weights: str | None = handed_in(BASELINE, default=None)
    # Stage 2: the Stage-1 adapter (folder or safetensors file) to clone; required for stage2.
    init_adapter: str | None = handed_in(BASELINE, default=None)
    # Save a resumable Lightning checkpoint every n optimizer steps (and at the end).
    checkpoint_every_n_steps: int = execution(default=50, range=at_least(1))
    # Step checkpoints kept besides last.ckpt: 1 = the latest, 0 = none, -1 = all (paper-scale adapter +
    # AdamW state is ~0.8 GB per checkpoint). Without a monitored metric Lightning allows only these.
    keep_checkpoints: int = execution(default=1, range=within(0, 1, -1))
    # Resume from this Lightning checkpoint ("last" = the run's own last.ckpt if it exists).
    resume_from: str | None = execution(default="last")
    # Export the exponential moving average of the trained weights (the baseline's, or the adapters') with this
    # decay, updated after every step (None = the last step's weights). Checkpoints carry the average and the
    # current weights; held_out_eval scores the current ones. The average is a second copy of the module (frozen
    # weights included), so it is for unsharded runs.
    ema_decay: float | None = reads(BASELINE, default=None, range=within(0, 1, high_open=True))
    # Deploy the in-training restorer on validation scenes and log its scores (off unless scenes are named).
    # It draws its own random streams: the weights are the same with or without it (so is held_out_eval).
    deployment_eval: DeploymentEvalConfig = execution(factory=DeploymentEvalConfig)
    # Stage 1 / 2: score the adapter on held-out clips while it trains (off unless a cache is named).
    held_out_eval: HeldOutEvalConfig = execution(factory=HeldOutEvalConfig)

    def __post_init__(self) -> None:
        self.name = StageName.parse(self.name, "stage.name")
        self.memory_mode = MemoryMode.parse(self.memory_mode, "stage.memory_mode")
        check_ranges(self, "stage")


@dataclass
class TeacherConfig:
    """Stage-2 teacher conditioning (Table 3): the teacher's R_d is the final render of a 3DGS fitted to
    ``views`` training views (None = all), for every student view count K.

    The teacher is privileged when ``views`` exceeds every student K (variants C, D, E, F: 12, 18, all).
    Variant B sets ``views`` to 3: a three-view teacher for every K in {3, 6, 9}, which carries no privileged
    geometry (at K = 6, 9 it sees fewer views than the student). It is not the student's own rendering: that
    changes with K and with the student's snapshot.
    """

    # Stage 1 aligns to this teacher's R_d.
    views: int | None = reads(STAGE1, default=None, range=at_least(1))


@dataclass
class PolicyConfig:
    """Where Stage 2 queries the teacher: student-visited states (on-policy) or forward-noised ones (E)."""

    on_policy: bool = reads(STAGE2, default=True)


@dataclass
class LossConfig:
    """Loss weights: Stage 1 L_warm (supplement Eq. supp-stage1), Stage 2 Eq. 9."""

    lambda_align: float = reads(STAGE1, default=1.0, range=at_least(0))
    lambda_ret: float = reads(STAGE2, default=0.15, range=at_least(0))
    trajectory_space: TrajectorySpace = reads(STAGE2, default=TrajectorySpace.velocity)
    trajectory_target: TrajectoryTarget = reads(STAGE2, default=TrajectoryTarget.teacher)
    # epsilon of the token-wise L2 normalisation (supplement Eq. supp-retrieval-normalization).
    retrieval_eps: float = reads(STAGE2, default=1e-6, range=positive())


@dataclass
class ClusterResources:
    """What one SLURM job running this trainer requests (read by conf/hydra/launcher/slurm.yaml)."""

    gpus_per_node: int = execution(default=0, range=at_least(0))
    cpus_per_task: int = execution(default=2, range=at_least(1))
    mem_gb: int = execution(default=8, range=at_least(1))
    timeout_min: int = execution(default=240, range=at_least(1))
    # The GPU check's JSON (launch/gpu_check.sh on this cluster's GPU) whose Stage-2 iteration the SLURM launcher's
    # requeue signal must leave time for (refused at launch otherwise); None: not checked.
    gpu_check: str | None = execution(default=None)


@dataclass
class FsdpConfig:
    """FSDP settings, read when ``trainer.strategy`` is "fsdp" (tracegs/training/strategy.py)."""

    # Module classes sharded as one FSDP unit each (the transformer block at paper scale).
    wrap_modules: list[str] = reads(BASELINE, factory=lambda: ["ReferenceGuidedBlock"])
    # Recompute each wrapped block's activations in backward (replaces diffusers' gradient checkpointing).
    activation_checkpointing: bool = reads(BASELINE, default=True)
    # Free each unit's gathered weights after its forward (full sharding; backward gathers them again), or
    # keep them until backward (less communication, more memory: ZeRO-2-like).
    reshard_after_forward: bool = reads(BASELINE, default=True)


@dataclass
class TrainerConfig:
    """Arguments forwarded to ``lightning.Trainer`` (paper scale: accelerator gpu, bf16-mixed, DDP)."""

    accelerator: str = reads(BASELINE, default="cpu")
    devices: str = reads(BASELINE, default="1")  # Lightning syntax: "1", "4", "auto", "0,1"
    num_nodes: int = reads(BASELINE, default=1, range=at_least(1))
    strategy: str = reads(BASELINE, default="auto")
    precision: str = reads(BASELINE, default="32-true")
    log_every_n_steps: int = execution(default=10, range=at_least(1))
    # Any of "csv", "tensorboard", "wandb" (wandb needs the optional extra).
    loggers: list[str] = execution(factory=lambda: ["csv", "tensorboard"])
    enable_progress_bar: bool = execution(default=True)
    deterministic: bool = reads(BASELINE, default=False)
    # torch intra-op threads per process of every command (None = torch's default); 1 when several ranks or runs
    # share the cores (more then spin in OpenMP barriers).
    cpu_threads: int | None = execution(default=None, range=at_least(1))
    # Debug switches (conf/debug): a one-step smoke run, overfitting one batch, anomaly detection, and every stage's
    # step budget (None: each stage's own, experiment.<stage>_steps). The budget is set here, not in the stage section,
    # so that a later stage's config still says what an earlier one ran (tracegs.pipeline.upstream).
    max_steps: int | None = via("stage.max_steps", default=None, range=at_least(1))
    fast_dev_run: int = reads(BASELINE, default=0, range=at_least(0))
    overfit_batches: float = reads(BASELINE, default=0.0, range=at_least(0))
    detect_anomaly: bool = reads(BASELINE, default=False)
    # Lightning owns SLURM requeueing: on this signal its SLURMEnvironment checkpoints (hpc_ckpt_<n>.ckpt in the
    # run folder, after the step in flight) and requeues; the requeued job resumes from its newest checkpoint.
    slurm_requeue_signal: str = execution(default="SIGUSR2")
    cluster: ClusterResources = execution(factory=ClusterResources)
    fsdp: FsdpConfig = reads(BASELINE, factory=FsdpConfig)


@dataclass
class TrainConfig:
    """Everything ``train_stage`` needs. The Hydra schema composes this from the config groups."""

    stage: StageConfig = field(default_factory=StageConfig)
    optimizer: OptimizerConfig = field(default_factory=OptimizerConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    teacher: TeacherConfig = field(default_factory=TeacherConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    data: DataModuleConfig = field(default_factory=DataModuleConfig)
    output_dir: str = "outputs/train"
    # What ``stage.deployment_eval`` deploys with: where its scenes are, the restore-refine loop and the 3DGS fit.
    source: SceneSourceConfig = field(default_factory=SceneSourceConfig)
    deploy: RefinementConfig = field(default_factory=RefinementConfig)
    fit: GaussianFitConfig = field(default_factory=GaussianFitConfig)
