"""``tracegs-replicate``: Table 3 of the paper measured at the embedded scale, over test scenes and training seeds.

Every variant of conf/ablation/ (or ``replicate.variants``) is trained and deployed on the same test scenes for
each training seed in ``replicate.training_seeds`` (root ``seed`` of those runs): A, the Stage-1 adapter and the
distilled students B ... F are trained from scratch once per seed, the students from that seed's Stage-1
adapter. Everything else is fixed by this run's own root ``seed`` and shared by every variant and replicate: the
synthetic scenes, the prepared training and held-out caches (prepared once, with every teacher condition the
chosen variants need: the 12- and 18-view teachers and B's 3-view teacher at the full scale), the 3DGS fits and
the deployment noise (``data.prepare.seed``, ``data.prepare.fit.seed`` and ``deploy.seed`` are pinned to this
seed's values). Plain 3DGS does not depend on the restorer and is evaluated once.

Each step is the command a user would type (``tracegs-prepare``, ``-train``, ``-evaluate``, ``-report``), run as
a child process with its overrides on its own command line, so each finds its upstream products exactly as when
typed by hand (tracegs.pipeline.upstream), and every step resumes when the command is rerun. A seed's
Stage-2 students and its evaluations are one multirun each (Hydra's local launcher), as
``launch/sweep_ablation.sh`` runs them: one interpreter start per step rather than per variant.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from tracegs.config.identity import derive_seed
from tracegs.config.overrides import override_key
from tracegs.config.tree import ConfigTree
from tracegs.console import show
from tracegs.errors import ConfigError
from tracegs.eval.html_report import write_report_page
from tracegs.eval.replicates import ReplicateInputs, write_replicate_report
from tracegs.io import write_json_atomic
from tracegs.pipeline.runner import Commands, Step, Sweep, run_steps
from tracegs.pipeline.steps import BASELINE_RUN, baseline_steps, data_steps, in_protocol_order
from tracegs.pipeline.variants import table3_configs, table3_names, teacher_settings
from tracegs.provenance import describe, peak_rss_gib
from tracegs.stages import Product, stage_table

log = logging.getLogger("tracegs")

# The student whose privileged gap the run record gives (TRACE-GS), with A's.
PRIVILEGED_VARIANT = "F"

# Rates behind the wall-time estimate printed before the run, on an idle 2-core machine of the README's kind
# (AMD EPYC, torch 2.13 CPU, the compiled rasterizer), fitted to the parts of a measured clean-clone run (the
# README's); the estimate multiplies them by this config's sizes. Machines of this kind, and one VM from hour to
# hour, differ by up to 2x.
FIT_ITERATION_S = 0.0068  # one 3DGS iteration at 48x72, one core
REFINE_ITERATION_S = 0.013  # one deployment iteration with restored pseudo views (a second render), one core
RESTORER_FORWARD_S = 0.034  # one tiny-restorer forward of one 9-frame 48x72 clip, one core
PREPARED_CONDITION_S = 0.029  # rendering and encoding one condition of one prepared clip
# Training wall time per sample (both cores) of the demo's batch of 4 at 48x72: A's step, Stage 1's step,
# and one state of Stage 2's rollout (student forward and backward, teacher forward).
BASELINE_SAMPLE_S = 0.062
STAGE1_SAMPLE_S = 0.090
STAGE2_SAMPLE_STATE_S = 0.062
PROCESS_START_S = 7.0  # a child command: interpreter, torch, Hydra, the restorer
JOB_START_S = 3.0  # one more job of a multirun in a running process (composition, restorer weights, lookups)
CORES = 2


@dataclass(frozen=True)
class Variant:
    """One Table 3 variant as tracegs-replicate runs it: whether it trains a Stage-2 student, the teacher's view
    count it is distilled from (None = all training views) and the evaluation method standing for it."""

    name: str
    trained: bool
    teacher_views: int | None
    method: str
    description: str


def replicate_variants(tree: ConfigTree, names: Sequence[str] | None = None) -> list[Variant]:
    """The variants of conf/ablation/ in Table 3's rows (``names``: only those), read from their configs."""
    if names is not None:
        unknown = sorted(set(names) - set(table3_names(tree)))
        if unknown:
            raise ConfigError("replicate.variants", f"{unknown} are not variants of conf/ablation/")
        if len(set(names)) != len(names):
            raise ConfigError("replicate.variants", f"{list(names)} repeats a variant")
        if not names:
            raise ConfigError("replicate.variants", "list at least one variant")
    return [Variant(cfg.ablation.name, bool(cfg.ablation.train_stage2), cfg.teacher.views, str(cfg.ablation.method),
                    cfg.ablation.description) for cfg in table3_configs(tree, names)]


def variant_teachers(variants: Sequence[Variant], student_views: Sequence[int]) -> dict[str, Any]:
    """The teacher conditions the chosen variants' students distil from (tracegs.pipeline.variants.teacher_settings),
    prepared once for every replicate."""
    return teacher_settings([v.teacher_views for v in variants if v.trained], student_views)


def replicate_steps(variants: Sequence[Variant], root_seed: int, training_seeds: Sequence[int], out_dir: Path,
                    user: Sequence[str] = (), held_out_clips_per_scene: int = 2,
                    views: Sequence[int] = (3,), student_views: Sequence[int] = (3, 6, 9),
                    pretrain: bool = True) -> list[Step]:
    """The steps of one tracegs-replicate run, in order: the data and A once (``pretrain``: A on its own scenes
    first, experiment.baseline_split), plain 3DGS once, then per training seed Stage 1, every student, every
    variant's deployment, the trajectory diagnostics and the privileged gap (see the module docstring for what is
    shared). ``user``: the command line's overrides, passed to every step."""
    if not training_seeds:
        raise ValueError("replicate.training_seeds: list at least one training seed")
    if len(set(training_seeds)) != len(training_seeds):
        raise ValueError(f"replicate.training_seeds: {list(training_seeds)} repeats a seed")
    train_cache, test_cache = out_dir / "cache" / "train", out_dir / "cache" / "test"
    shared = {"experiment": "replicate",
              "data.prepare.seed": derive_seed(root_seed, "prepare"),
              "data.prepare.fit.seed": derive_seed(root_seed, "fit"),
              "deploy.seed": derive_seed(root_seed, "deploy"),
              "evaluation.views": list(views),
              **variant_teachers(variants, student_views)}
    names = Sweep(tuple(v.name for v in variants))
    trained = Sweep(tuple(v.name for v in variants if v.trained))
    # A is made once, from this run's root seed, and frozen (the paper's A is one released model); with the paper's
    # data protocol it is trained before the training clips, whose pseudo-targets it makes.
    root = {**shared, "seed": root_seed}
    data = data_steps(
        common=root, training={"data.prepare.cache_dir": train_cache},
        held_out={"data.prepare.clips_per_scene": held_out_clips_per_scene, "data.prepare.cache_dir": test_cache,
                  # The diagnostics restore the held-out clips at the deployed view counts only.
                  "data.prepare.student_views": list(views)})
    steps = in_protocol_order(pretrain, baseline_steps(pretrain, root), data)
    # Fig. 6 comes from the held-out clips (the diagnostics), so deployment computes no per-step curves.
    deployment = {"evaluation.per_step": False}
    steps.append(Step.of("evaluate", "evaluate plain 3DGS", shared, {"seed": root_seed},
                         {"evaluation.methods": ["3dgs"]}, deployment,
                         {"evaluation.out_dir": three_dgs_dir(out_dir)}))
    frozen_a = {"artifacts.baseline_weights": f"{BASELINE_RUN}/{stage_table().stage(Product.baseline).folder}"}
    for seed in training_seeds:
        common = {**shared, "seed": seed, "data.datamodule.cache_dir": train_cache}

        def multirun(kind: str, seed: int = seed) -> dict[str, Path]:
            return {"hydra.sweep.dir": out_dir / "multirun" / f"seed{seed}" / kind}

        steps.append(Step.of("train", f"seed {seed}: train Stage 1", common, {"stage": Product.stage1}, takes=frozen_a))
        if trained.values:
            steps.append(Step.of("train", f"seed {seed}: train Stage 2 ({','.join(trained.values)})",
                                 multirun("stage2"), common, {"stage": Product.stage2, "ablation": trained},
                                 takes=frozen_a))
        # Each variant is deployed by the method standing for it (A: the baseline restorer; else its student), into
        # the seed's folder of its name.
        steps.append(Step.of("evaluate", f"seed {seed}: evaluate ({','.join(names.values)})", multirun("evaluate"),
                             common, {"ablation": names, "evaluation.methods": ["${ablation.method}"]}, deployment,
                             {"evaluation.out_dir": f"{eval_dir(out_dir, seed)}/${{ablation.name}}"}, takes=frozen_a))
        steps.append(Step.of("report", f"seed {seed}: trajectory diagnostics", common,
                             {"report.kind": "diagnostics", "report.inputs": list(names.values),
                              "evaluation.held_out_cache": test_cache,
                              "report.output_dir": diagnostics_dir(out_dir, seed)}, takes=frozen_a))
        if PRIVILEGED_VARIANT in trained.values:
            steps.append(Step.of("report", f"seed {seed}: privileged gap", common,
                                 {"report.kind": "privileged", "ablation": PRIVILEGED_VARIANT,
                                  "evaluation.held_out_cache": test_cache,
                                  "report.output_dir": privileged_dir(out_dir, seed)}, takes=frozen_a))
    return [step.passing(user) for step in steps]


def eval_dir(out_dir: Path, seed: int) -> Path:
    """The seed's evaluations, one folder per variant."""
    return out_dir / "eval" / f"seed{seed}"


def three_dgs_dir(out_dir: Path) -> Path:
    return out_dir / "eval" / "3dgs"


def privileged_dir(out_dir: Path, seed: int) -> Path:
    return out_dir / "privileged" / f"seed{seed}"


def diagnostics_dir(out_dir: Path, seed: int) -> Path:
    return out_dir / "diagnostics" / f"seed{seed}"


def estimate_minutes(cfg: DictConfig, variants: Sequence[Variant], steps: Sequence[Step]) -> dict[str, float]:
    """Wall time on an idle 2-core machine, in minutes per part of the run: the module's rates times this
    config's sizes (fits and their iterations, clips and their conditions, training steps and batch, deployment
    rounds and reverse steps)."""
    prepare, fit, deploy, exp = cfg.data.prepare, cfg.data.prepare.fit, cfg.deploy, cfg.experiment
    views, seeds = list(cfg.evaluation.views), len(cfg.replicate.training_seeds)
    train_scenes, test_scenes = len(cfg.data.synthetic.train_seeds), len(cfg.data.synthetic.test_seeds)
    trained = sum(v.trained for v in variants)
    teachers = variant_teachers(variants, list(prepare.student_views))
    dense = len(teachers["data.prepare.dense_views"])
    final = teachers["data.prepare.student_final_fits"]
    sparse_iterations = fit.iterations if final else max(prepare.student_snapshots)
    snapshots = len(prepare.student_snapshots)

    def prepare_s(scenes: int, student_views: int, clips: int, teachers: int = dense) -> float:
        fits = scenes * (student_views * sparse_iterations + teachers * fit.iterations) * FIT_ITERATION_S / CORES
        # Each clip: the student conditions, the teachers (and the final snapshots), the target.
        conditions = student_views * snapshots + teachers + (student_views if final else 0) + 1
        return fits + scenes * clips * conditions * PREPARED_CONDITION_S

    reverse_steps = deploy.steps or cfg.backbone.schedule.deploy_steps
    data = (prepare_s(train_scenes, len(prepare.student_views), exp.clips_per_scene)
            + prepare_s(test_scenes, len(views), cfg.replicate.held_out_clips_per_scene))
    if exp.baseline_split == "pretrain":  # A's own scenes (sparse fits only), and A restoring every R_d
        data += prepare_s(len(cfg.data.synthetic.pretrain_seeds), len(prepare.student_views),
                          prepare.pretrain_clips_per_scene or exp.clips_per_scene, teachers=0)
    if prepare.pseudo_target == "restorer":
        data += train_scenes * exp.clips_per_scene * reverse_steps * RESTORER_FORWARD_S / CORES
    baseline = exp.batch_size * exp.baseline_steps * BASELINE_SAMPLE_S  # once: A is frozen for every seed
    training = seeds * (exp.batch_size * exp.stage1_steps * STAGE1_SAMPLE_S
                        + exp.stage2_batch_size * trained * exp.stage2_steps * cfg.stage.rollout_steps
                        * STAGE2_SAMPLE_STATE_S)
    units = test_scenes * len(views)
    cold_start = deploy.repair_iters[0] * FIT_ITERATION_S
    after_cold = deploy.total_iters - deploy.repair_iters[0]
    clips_per_round = deploy.max_clips_per_round or max(views)
    restorer_method = (after_cold * REFINE_ITERATION_S
                       + len(deploy.repair_iters) * clips_per_round * reverse_steps * RESTORER_FORWARD_S)
    workers = min(cfg.evaluation.workers, CORES)
    deployment = (units * (cold_start + after_cold * FIT_ITERATION_S)
                  + seeds * len(variants) * units * (cold_start + restorer_method)) / workers
    # Diagnostics: per held-out clip and variant, the rollout and the forward-noised predictions (and the
    # teacher's for a distilled variant), each over the clip's student conditions at the deployed view counts.
    clip_conditions = len(views) * snapshots
    forwards = reverse_steps * clip_conditions * (2 * len(variants) + trained)
    # The privileged gap: A, the Stage-1 adapter and F restore each clip from R_d and from its student conditions.
    if any(v.name == PRIVILEGED_VARIANT and v.trained for v in variants):
        forwards += 3 * reverse_steps * (1 + clip_conditions)
    diagnostics = seeds * test_scenes * cfg.replicate.held_out_clips_per_scene * forwards * RESTORER_FORWARD_S / workers
    # The multiruns' further jobs, and the diagnostics' composition of each variant's config and its upstream.
    jobs = seeds * (trained + 2 * len(variants))
    starts = len(steps) * PROCESS_START_S + jobs * JOB_START_S
    parts = {"data": data, "A": baseline, "training": training, "deployment": deployment, "diagnostics": diagnostics,
             "process starts": starts}
    return {part: seconds / 60 for part, seconds in parts.items()}


def replicate(cfg: DictConfig) -> Path:
    """Run every step (each resumes when rerun), then write ``replicate.md`` and ``run.json`` into
    ``cfg.run_dir``."""
    out_dir = Path(cfg.run_dir).resolve()
    seeds = list(cfg.replicate.training_seeds)
    variants = replicate_variants(ConfigTree.of(cfg),
                                  None if cfg.replicate.variants is None else list(cfg.replicate.variants))
    user = [o for o in cfg.command_line
            if override_key(o).split(".")[0] not in ("replicate", "seed", "ablation")]
    clips = cfg.replicate.held_out_clips_per_scene
    steps = replicate_steps(variants, cfg.seed, seeds, out_dir, user, clips, list(cfg.evaluation.views),
                            list(cfg.data.prepare.student_views), cfg.experiment.baseline_split == "pretrain")
    parts = estimate_minutes(cfg, variants, steps)
    estimate = sum(parts.values())
    show(f"tracegs-replicate: Table 3 ({', '.join(v.name for v in variants)}) x training seeds {seeds} on "
         f"{len(cfg.data.synthetic.test_seeds)} test scenes at {list(cfg.evaluation.views)} views: {len(steps)} "
         f"steps, about {estimate:.0f} min on an idle 2-core machine ("
         + ", ".join(f"{part} {minutes:.1f}" for part, minutes in parts.items())
         + f"; up to twice that on a slow one); output in {out_dir}")
    start = time.perf_counter()
    timings = run_steps(steps, Commands("local"), "replicate")
    wall_s = time.perf_counter() - start
    run = {**describe(cfg.seed), "training_seeds": seeds, "variants": [v.name for v in variants],
           "wall_s": round(wall_s, 1), "table3_minutes": round(wall_s / 60, 1),
           "peak_rss_gib": round(peak_rss_gib(), 3), "step_s": timings, "estimate_min": round(estimate, 1),
           "stage2_steps": cfg.experiment.stage2_steps,
           "estimate_parts_min": {part: round(minutes, 1) for part, minutes in parts.items()}}
    machine = run["machine"]
    header = (f"# Table 3 replicated over training seeds (embedded scale)\n\nCommit {run['commit']}, {machine['cpu']} ({machine['cores']} "
              f"cores, torch {machine['torch']}): wall time {run['table3_minutes']:.1f} min (estimated "
              f"{estimate:.0f}), peak RSS {run['peak_rss_gib']:.2f} GiB (largest step). Data, 3DGS fits and "
              f"deployment noise from seed {cfg.seed}; A trained once from it and frozen, Stage 1 and every "
              "student trained from scratch for each training seed.\n")
    inputs = ReplicateInputs(seeds=seeds, variants=[v.name for v in variants],
                             descriptions={v.name: v.description for v in variants},
                             methods={v.name: v.method for v in variants},
                             eval_dirs={s: eval_dir(out_dir, s) for s in seeds}, three_dgs_dir=three_dgs_dir(out_dir),
                             diagnostics_dirs={s: diagnostics_dir(out_dir, s) for s in seeds},
                             privileged_dirs={s: privileged_dir(out_dir, s) for s in seeds
                                              if PRIVILEGED_VARIANT in [v.name for v in variants if v.trained]})
    report, figures = write_replicate_report(out_dir, inputs, header)
    write_json_atomic({**run, **figures}, out_dir / "run.json")
    page = write_report_page(out_dir)
    show(report.read_text())
    show(f"tracegs-replicate: the tables, Fig. 6 and the evaluations' pages in {page}")
    return report
