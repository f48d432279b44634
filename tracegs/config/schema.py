"""Typed Hydra schema: every config file in ``conf/`` merges into these dataclasses.

Each package owns the dataclasses of its hyperparameters (``tracegs.<package>.config``); this module
only composes them into one root node and registers it in Hydra's ConfigStore, so a misspelt key or a
value of the wrong type fails at composition with the field named (OmegaConf struct mode).
Cross-field rules that types cannot express live in :mod:`tracegs.config.validate`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from tracegs.config.identity import SCHEMA_NAME, register_resolvers
from tracegs.data.config import DataModuleConfig, PrepareConfig, SceneSourceConfig, Split, SyntheticConfig
from tracegs.deploy.config import CaptureConfig, EvaluationConfig, RefinementConfig
from tracegs.modes import Mode
from tracegs.products import (
    BASELINE,
    DEPLOYMENT,
    PREPARE,
    RESTORE,
    STAGE1,
    STAGE2,
    declarations,
    execution,
    reads,
)
from tracegs.ranges import SEED, at_least, each, positive, ranges, within
from tracegs.restorer.config import BackboneConfig, SamplerConfig
from tracegs.splat.config import GaussianFitConfig
from tracegs.training.config import (
    LossConfig,
    OptimizerConfig,
    PolicyConfig,
    StageConfig,
    TeacherConfig,
    TrainerConfig,
)


class Task(Mode):
    """The entry point a composed config belongs to (``conf/<task>.yaml``)."""

    prepare = "prepare"
    train = "train"
    deploy = "deploy"
    evaluate = "evaluate"
    restore = "restore"
    report = "report"
    demo = "demo"
    replicate = "replicate"


class ReportKind(Mode):
    """What ``tracegs-report`` merges (tracegs.pipeline.report)."""

    main = "main"  # evaluation shards -> results.json (Tables 1/2)
    ablation = "ablation"  # an ablation sweep -> Table 3
    per_step = "per_step"  # Fig. 6 across variants on the held-out clips
    seeds = "seeds"  # several demo runs -> mean, sd and range of each figure
    privileged = "privileged"  # restorations from R_d vs R_s on the held-out clips (the privileged gap)
    diagnostics = "diagnostics"  # exposure gap and teacher advantage per variant and reverse step (held-out clips)


class EvaluatedMethod(Mode):
    """The restorer that stands for a Table 3 variant in evaluation."""

    baseline = "baseline"
    tracegs = "tracegs"


@dataclass
class PathsConfig:
    """Where inputs are read and outputs land (all relative to the launch directory by default)."""

    root_dir: str = execution(default=".")
    data_dir: str = execution(default="${paths.root_dir}/data")
    # Local model weights (diffusers / transformers dirs)
    weights_dir: str = execution(default="${paths.root_dir}/weights")
    runs_dir: str = execution(default="${paths.root_dir}/outputs")  # one sub-folder per experiment
    # Shared artefacts of one experiment (baseline weights, the Stage-1 adapter every ablation clones).
    experiment_dir: str = execution(default="${paths.runs_dir}/${experiment.name}")


def seeded(stream: str) -> Any:
    """A part's ``seed`` field derived from the root ``seed`` (see :mod:`tracegs.config.identity`)."""
    return f"${{tracegs.seed:{stream}}}"


# The paired-clip cache of a split is named by its run identity, so changed preparation settings or another
# seed never reuse a cache; training always reads the train split's cache of the same settings.
CACHE_ROOT = "${paths.data_dir}/cache/${data.name}-${backbone.name}"


@dataclass
class DataConfig:
    """Scene source, synthetic benchmark, paired-clip preparation and the DataModule."""

    name: str = reads(PREPARE, BASELINE, default="synthetic")
    source: SceneSourceConfig = reads(PREPARE, BASELINE, factory=SceneSourceConfig)
    synthetic: SyntheticConfig = reads(PREPARE, BASELINE, factory=SyntheticConfig)
    prepare: PrepareConfig = reads(PREPARE, BASELINE, factory=lambda: PrepareConfig(
        cache_dir="${tracegs.product:" + CACHE_ROOT + "-${data.prepare.split}-${tracegs.cache:${data.prepare.split}}}",
        work_dir="${tracegs.product:${paths.data_dir}/prepare_work/${data.name}-${data.prepare.split}-"
                 "${tracegs.cache:${data.prepare.split}}}",
        seed=seeded("prepare"), fit=GaussianFitConfig(seed=seeded("fit"))))
    datamodule: DataModuleConfig = reads(BASELINE, factory=lambda: DataModuleConfig(
        cache_dir="${tracegs.product:" + CACHE_ROOT + "-train-${tracegs.cache:train}}", seed=seeded("datamodule")))


AUTO = "auto"


@dataclass
class ArtifactsConfig:
    """Products of earlier stages that later tasks load, at fixed places under the experiment folder."""

    # Each is "auto" (the product of the run that the run-identity rule finds for this configuration, see
    # tracegs.pipeline.upstream.locate_artifacts) or an explicit path.
    # Variant A's transformer (a diffusers directory written by ``stage=baseline``). null = the backbone's
    # own ``transformer.pretrained_path`` (paper scale: GSFixer's pretrained restorer is variant A).
    baseline_weights: str | None = reads(STAGE1, default=AUTO)
    # The aligned Stage-1 adapter every Stage-2 variant clones.
    stage1_adapter: str = reads(STAGE2, default=AUTO)
    # The deployed student adapter of the selected ablation variant.
    student_adapter: str = reads(DEPLOYMENT, default=AUTO)


@dataclass
class ExperimentConfig:
    """Which scale the run uses. Every value comes from the ``experiment`` group file (conf/experiment/:
    embedded, paper, rehearsal), the one place each scale's numbers are written."""

    name: str = reads(BASELINE, default=MISSING)
    description: str = execution(default=MISSING)
    # Per-scale training budgets that the ``stage`` group files read (supplement A.4); keeping them here
    # lets ``experiment=paper stage=stage1`` and ``experiment=paper stage=stage2`` each pick their own.
    # 0 = variant A is a pretrained restorer, loaded and never trained
    baseline_steps: int = reads(BASELINE, default=MISSING, range=at_least(0))
    baseline_lr: float = reads(BASELINE, default=MISSING, range=positive())
    # The baseline exports its weights' moving average (stage.ema_decay)
    baseline_ema_decay: float | None = reads(BASELINE, default=None, range=within(0, 1, high_open=True))
    # A trains the whole transformer and never reads a later stage's budget; Stage 1 never reads Stage 2's, so a
    # Stage-2 sweep reuses one A and one Stage-1 adapter.
    stage1_steps: int = reads(STAGE1, default=MISSING, range=at_least(1))
    stage2_steps: int = reads(STAGE2, default=MISSING, range=at_least(1))
    stage2_warmup_steps: int = reads(STAGE2, default=MISSING, range=at_least(0))
    stage1_lr: float = reads(STAGE1, default=MISSING, range=positive())
    stage2_lr: float = reads(STAGE2, default=MISSING, range=positive())
    batch_size: int = reads(BASELINE, default=MISSING, range=at_least(1))  # per device (A and Stage 1)
    # per device; a Stage-2 sample is N rollout states, not one
    stage2_batch_size: int = reads(STAGE2, default=MISSING, range=at_least(1))
    # Per-scale sizes that every ``data`` option reads, so any dataset composes with either scale.
    # rendered frames and resized images
    frame_height: int = reads(BASELINE, default=MISSING, range=at_least(1))
    frame_width: int = reads(BASELINE, default=MISSING, range=at_least(1))
    # 8k+1 frames per paired clip and deployment clip
    frames_per_clip: int = reads(BASELINE, default=MISSING, range=at_least(1))
    # paired clips prepared per scene (what Stage 2 reads)
    clips_per_scene: int = reads(BASELINE, default=MISSING, range=at_least(1))
    # A and Stage 1 read only each scene's first n of them (None: all), so Stage 2 can draw fresh clips from
    # the same cache without changing what A and Stage 1 were trained on.
    baseline_clips_per_scene: int | None = reads(BASELINE, default=None, range=at_least(1))
    # The scenes A is trained on (conf/stage/baseline.yaml reads that split's cache): ``pretrain``, scenes of its
    # own, as GSFixer was trained before TRACE-GS froze it, so that Stage 1 and 2 see the training scenes only
    # through pseudo-targets (the paper's protocol; the embedded default); ``train``, the training scenes' ground
    # truth (experiment=embedded_gt_targets: A is then the in-domain ceiling no student of R_s can pass).
    baseline_split: Split = reads(BASELINE, default=Split.train)


@dataclass
class AblationConfig:
    """One row of Table 3; the ``ablation`` group file (conf/ablation/) sets it and teacher/policy/loss."""

    name: str = reads(STAGE2, default=MISSING)
    description: str = execution(default=MISSING)
    # Its row in Table 3: the sweep trains and the report lists the variants in this order.
    row: int = execution(default=MISSING, range=at_least(1))
    # Variant A evaluates the frozen baseline restorer and trains nothing.
    train_stage2: bool = execution(default=MISSING)
    # The evaluation method that stands for this variant in Table 3 (variant A: the baseline restorer);
    # a sweep evaluates only it: 'evaluation.methods=[${ablation.method}]'.
    method: EvaluatedMethod = execution(default=EvaluatedMethod.tracegs)


@dataclass
class ReportConfig:
    """What ``tracegs-report`` merges (see :class:`ReportKind`)."""

    kind: ReportKind = execution(default=ReportKind.main)
    inputs: list[str] = execution(factory=list)  # result folders; empty = the experiment's defaults
    # Table 3's datasets (``data`` options), one column group each: the sweep's evaluations on each of them.
    datasets: list[str] = execution(factory=lambda: ["${data.name}"])
    # Tables 1/2's datasets (``data`` options): on each, one evaluation of plain 3DGS, A and TRACE-GS (F) merged by
    # report.kind=main (tracegs.pipeline.steps.main_table_steps).
    main_datasets: list[str] = execution(factory=lambda: ["${data.name}"])
    # report.kind=main: take A's and the variant's (F) scores from the ablation sweep's evaluations on this dataset
    # instead of evaluating them again (this command's own evaluation then holds 3DGS only).
    main_from_sweep: bool = execution(default=False)
    # report.kind=diagnostics and privileged: also restore with the Stage-1 adapter alone (the students' starting
    # point, a row named by the Stage-1 product), and give each student's final sample against it, paired over
    # scenes.
    stage1_row: bool = execution(default=False)
    output_dir: str = execution(default="${paths.experiment_dir}/report")


@dataclass
class ReplicateConfig:
    """``tracegs-replicate``: the restorer trained from scratch once per training seed, on data, 3DGS fits and
    deployment noise that the root ``seed`` fixes for every replicate (so plain 3DGS is computed once)."""

    training_seeds: list[int] = execution(factory=lambda: [0, 1, 2], range=each(SEED))
    # Clips per held-out scene (the training scenes keep experiment.clips_per_scene): the trajectory diagnostics
    # cost each variant about three restorations of every clip, their largest share after deployment.
    held_out_clips_per_scene: int = execution(default=2, range=at_least(1))
    # The Table 3 variants to train and deploy (names of conf/ablation/ files); None = every one of them.
    variants: list[str] | None = execution(default=None)


@dataclass
class ProcessesConfig:
    """The processes one job of a command runs (what a SLURM job asks for: nodes, tasks per node). Training runs a
    rank per device (conf/train.yaml: trainer.num_nodes x trainer.devices); every other command is one process on
    one device, with no rank logic, so its cluster job asks for one task."""

    nodes: int = execution(default=1, range=at_least(1))
    per_node: int = execution(default=1, range=at_least(1))


@dataclass
class TraceGSConfig:
    """Root of every composed config (prepare, train, deploy, evaluate, report, demo)."""

    task: Task = execution(default=MISSING)  # set by each entry point's conf/<task>.yaml
    # The root of every random stream (scene fits, clip sampling, noise, dropout, deployment).
    seed: int = reads(PREPARE, BASELINE, default=0, range=SEED)
    # The ``data`` option the restorers are trained on (the experiment chooses it). Training runs on it; ``data``
    # names what a command prepares, deploys or evaluates, so evaluating another dataset (``data=mipnerf360``)
    # loads the students trained on this one (tracegs.pipeline.upstream).
    # Deployment and evaluation read it: it selects the restorers they load.
    training_data: str = reads(DEPLOYMENT, default=MISSING)
    # Where this task writes its artefacts (also Hydra's run dir). Named by the run's identity rather than
    # timestamped, so later stages find earlier products and an interrupted run resumes in place.
    run_dir: str = execution(default="${paths.experiment_dir}/${task}")
    # The overrides this command was given on its command line (the entry point sets them; an in-process step
    # gets its own): an in-process runner composes each of its steps from them (tracegs.pipeline.runner). What a
    # product is, and where an earlier one lies (tracegs.pipeline.upstream), never depends on them.
    command_line: list[str] = execution(factory=list)
    # The config search path this command composed on (tracegs.config.tree): the lookups of other configs of the
    # tree (a variant's sections, a stage option) read the same files with no Hydra context open.
    config_search_path: list[str] = execution(factory=list)
    # What a cluster job of this command is called (SLURM job name): the command, stage and variant.
    job_name: str = execution(default="${task}-${stage.name}-${ablation.name}")
    processes: ProcessesConfig = execution(factory=ProcessesConfig)
    paths: PathsConfig = execution(factory=PathsConfig)
    artifacts: ArtifactsConfig = reads(STAGE1, factory=ArtifactsConfig)
    experiment: ExperimentConfig = reads(BASELINE, factory=ExperimentConfig)
    backbone: BackboneConfig = reads(
        PREPARE, BASELINE, factory=lambda: BackboneConfig(sampler=SamplerConfig(seed=seeded("sampler"))))
    data: DataConfig = reads(PREPARE, BASELINE, factory=DataConfig)
    stage: StageConfig = reads(BASELINE, factory=lambda: StageConfig(seed=seeded("training")))
    optimizer: OptimizerConfig = reads(BASELINE, factory=OptimizerConfig)
    teacher: TeacherConfig = reads(STAGE1, factory=TeacherConfig)
    policy: PolicyConfig = reads(STAGE2, factory=PolicyConfig)
    loss: LossConfig = reads(STAGE1, factory=LossConfig)
    trainer: TrainerConfig = reads(BASELINE, factory=TrainerConfig)
    ablation: AblationConfig = reads(STAGE2, factory=AblationConfig)
    deploy: RefinementConfig = reads(DEPLOYMENT, factory=lambda: RefinementConfig(seed=seeded("deploy")))
    evaluation: EvaluationConfig = reads(DEPLOYMENT, factory=EvaluationConfig)
    report: ReportConfig = execution(factory=ReportConfig)
    capture: CaptureConfig = reads(RESTORE, factory=CaptureConfig)  # tracegs-restore's own scene
    replicate: ReplicateConfig = execution(factory=ReplicateConfig)


def register_configs(schema: type = TraceGSConfig) -> None:
    """Register the root schema so primary configs can list it first in their defaults. A field that declares no
    products (tracegs.products), or a numeric one that declares no range (tracegs.ranges), is refused here, before
    any config is composed."""
    declarations(schema)
    ranges(schema)
    register_resolvers()
    ConfigStore.instance().store(name=SCHEMA_NAME, node=schema)
