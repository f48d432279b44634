"""Estimated GPU hours of each paper-scale command that makes Tables 1-3 and Fig. 6, in the order a group runs them.

Usage: ``.venv/bin/python benchmarks/paper_gpu_hours.py [--train-scenes 112] [--dl3dv-test-scenes 28]
[--measured outputs/gpu_check/gpu_check.json] [extra overrides for every command, e.g. trainer.devices=8]``

The commands are the pipeline's own: ``tracegs-prepare experiment=paper`` (the training cache with every teacher of
Table 3), then the Table 3 sweep (``tracegs.pipeline.steps.sweep_steps``, as ``launch/sweep_ablation.sh slurm
experiment=paper`` runs it: evaluations at ``evaluation.views`` (3/6/9) on Table 3's ``report.datasets``, DL3DV and
Mip-NeRF 360), then Tables 1/2 (``tracegs.pipeline.steps.main_table_steps``): plain 3DGS, A and TRACE-GS (F) on each
dataset of ``report.main_datasets`` (DL3DV, Mip-NeRF 360 and NeRFBusters), A and F read from the sweep's evaluations
where it made them (only 3DGS evaluated again there), in one evaluation of the three elsewhere. Each job's config
is composed as its command line composes it, and the work it does is counted from that config with the functions
the code runs (``clip_view_counts``, ``clip_condition_keys``, ``reference_pairs``): 3DGS iterations, rendered frames,
captions, VAE encodes and decodes, transformer forwards (no gradient) and training forwards (with gradient). The
rehearsal (``experiment=rehearsal``) runs these same code paths at shrunk sizes; its Stage-2 test counts the N
student forwards with gradient and N teacher forwards per step that this estimate counts.

Seconds per unit (``UnitSeconds``) are estimates for one A100, each naming its source, unless ``--measured`` gives
the JSON of ``benchmarks/gpu_check.py`` run on a GPU: then every unit it measured (transformer forward, training
factor, VAE encode and decode) is that GPU's, the training factor from the fastest Stage-2 iteration measured (the
``stage2`` section's as configured, or a setting of its ``speed`` section: the transformer's switches), and the
printout says which units are measured on which device, with which Stage-2 setting, and which are still assumed. Even measured, the GPU hours are an estimate of the order of magnitude, to plan a cluster allocation and to compare with
the paper's "approximately five days end to end" on four A100s for the training-data preprocessing and the
2,000 Stage-2 iterations (supplement, computational cost: 480 GPU hours).

The last line is one JSON object: ``gpu_hours`` per command label, ``gpu_hours_total``,
``gpu_hours_paper_scope`` (preparation with F's teacher alone + Stage 1 + one Stage-2 student, the scope of the
paper's five days) beside ``paper_gpu_hours`` (480), and
``unit_seconds`` with their ``unit_sources``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from tracegs.config.schema import register_configs
from tracegs.config.tree import ConfigTree
from tracegs.data.colmap import read_scene_list
from tracegs.data.config import PrepareConfig
from tracegs.data.preparation.plan import (
    captures_held_out,
    clip_condition_keys,
    clip_view_counts,
    teacher_view_counts,
    trajectory_count,
)
from tracegs.location import CONF_DIR
from tracegs.pipeline.runner import Step, override
from tracegs.pipeline.steps import main_table_steps, sweep_steps
from tracegs.pipeline.variants import per_step_variants, table3_configs, table3_variants, variants_teachers
from tracegs.splat.trajectory import clips_per_round, reference_pairs
from tracegs.stages import Product

HOUR = 3600.0
# The supplement's computational cost: "approximately five days" on four A100s for the training-data preprocessing
# and the 2,000 Stage-2 iterations, at most 5 x 24 x 4 GPU hours.
PAPER_GPU_HOURS = 480
PAPER_JOB = ("experiment=paper", "trainer=ddp")  # what every counted command composes (a cluster job at paper scale)


@dataclass(frozen=True)
class UnitSeconds:
    """Seconds per unit of work on one GPU. The defaults are estimates for one A100 80 GB, each with its source;
    ``measured`` replaces those that ``benchmarks/gpu_check.py`` measured."""

    # CogVideoX-5B-I2V's model card: ~180 s for 50 steps at 49x480x720 in bf16 on one A100, classifier-free
    # guidance on (100 clip forwards, VAE decoding included): at most 1.8 s per clip forward; GSFixer's
    # cross-attention adds little.
    transformer_forward: float = 1.8
    # A forward with gradient plus its backward (twice a forward), plus the recomputation of activation checkpointing
    # (backbone.transformer.activation_checkpointing: 1 at paper scale): four forwards.
    training_forward_factor: float = 4.0
    vae_encode: float = 3.0  # assumed: CogVideoX's 3D VAE, one 49-frame clip
    vae_decode: float = 6.0  # assumed: decoding is tiled and the slower direction
    caption: float = 0.3  # assumed: BLIP-2 OPT-2.7B, one caption
    render_frame: float = 0.01  # assumed: gsplat render of one 480x720 frame of a few million Gaussians
    # 3DGS: NerfBaselines' Mip-Splatting runs on Mip-NeRF 360 took 1,200-1,800 s for 30k iterations; gsplat reports
    # up to 2x less time than the original rasterizer: ~20 min per 30k. The GPU check's fit runs on a small
    # procedural scene, whose speed says nothing of a dense capture's: this one stays an estimate.
    fit_iteration: float = 0.04
    refine_iteration_factor: float = 2.0  # a refinement iteration renders and back-propagates a second (pseudo) view

    @classmethod
    def measured(cls, record: dict) -> tuple[UnitSeconds, dict[str, str]]:
        """The units ``gpu_check.json`` (``record``) measured replace the estimates; returns them and, per unit,
        where its value comes from."""
        restorer, vae, stage2 = (record.get(name, {}) for name in ("restorer", "vae", "stage2"))
        device = record.get("device", {}).get("name", "unknown device")
        values: dict[str, float] = {}
        if "rollout_step" in restorer:  # one clip forward, no gradient
            values["transformer_forward"] = restorer["rollout_step"]["seconds"]
        fastest = fastest_stage2(record)
        if fastest is not None and "rollout_step" in restorer:
            # One iteration = batch x N x (a student forward with gradient and its backward + a teacher forward).
            forward = restorer["rollout_step"]["seconds"]
            values["training_forward_factor"] = max(fastest[1] - forward, forward) / forward
        for unit in ("vae_encode", "vae_decode"):
            if unit in vae:
                values[unit] = vae[unit]["seconds"]
        sources = {f.name: (f"measured on {device}" if f.name in values else "assumed (one A100)")
                   for f in fields(cls)}
        if "training_forward_factor" in values:
            sources["training_forward_factor"] += f" (Stage 2 {fastest[0]})"
            if fastest[0] == STAGE2_AS_CONFIGURED and len(stage2.get("iterations", [])) == 1:
                sources["training_forward_factor"] += " (first iteration only: AdamW's state allocated in it)"
        return replace(cls(), **values), sources


STAGE2_AS_CONFIGURED = "as configured"


def fastest_stage2(record: dict) -> tuple[str, float] | None:
    """(setting, seconds per visited state) of the fastest Stage-2 iteration ``gpu_check.json`` measured: the
    ``stage2`` section's (as configured, at the paper's N) or a setting of the ``speed`` section (its switches, at
    its own N); None when neither measured one."""
    per_state: dict[str, float] = {}
    stage2, speed = record.get("stage2", {}), record.get("speed", {})
    if "iteration" in stage2:
        per_state[STAGE2_AS_CONFIGURED] = stage2["iteration"]["seconds"] / (stage2["batch_size"]
                                                                            * stage2["rollout_steps"])
    for name, figures in speed.items():
        if isinstance(figures, dict) and "seconds" in figures:  # a setting measured (not its error)
            per_state[f"with speed setting {name}"] = figures["seconds"] / (speed["batch_size"]
                                                                           * speed["rollout_steps"])
    if not per_state:
        return None
    best = min(per_state, key=per_state.get)
    return best, per_state[best]


@dataclass
class Work:
    """What one job does, in units of the per-unit costs above."""

    fit_iterations: float = 0.0
    refine_iterations: float = 0.0
    rendered_frames: float = 0.0
    captions: float = 0.0
    encodes: float = 0.0
    decodes: float = 0.0
    forwards: float = 0.0
    training_forwards: float = 0.0

    def __add__(self, other: Work) -> Work:
        return Work(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))

    def scaled(self, factor: float) -> Work:
        return Work(*(getattr(self, f.name) * factor for f in fields(self)))

    def gpu_hours(self, unit: UnitSeconds = UnitSeconds()) -> float:
        seconds = (self.fit_iterations * unit.fit_iteration
                   + self.refine_iterations * unit.fit_iteration * unit.refine_iteration_factor
                   + self.rendered_frames * unit.render_frame + self.captions * unit.caption
                   + self.encodes * unit.vae_encode + self.decodes * unit.vae_decode
                   + (self.forwards + self.training_forwards * unit.training_forward_factor) * unit.transformer_forward)
        return seconds / HOUR


def guided(scale: float) -> int:
    """Clip forwards per denoising step: classifier-free guidance evaluates the unconditional branch too."""
    return 2 if scale > 1.0 else 1


def clip_views(cfg: DictConfig) -> list[int]:
    """The student view count K of each clip of one scene: the training clips divided among the K, or the held-out
    clips through captured cameras (every reference pair of every K)."""
    prepare: PrepareConfig = OmegaConf.to_object(cfg.data.prepare)
    if captures_held_out(OmegaConf.to_object(cfg.data.source), prepare):
        return [k for k in prepare.student_views for _ in reference_pairs(k, None, torch.Generator())]
    return clip_view_counts(prepare, "scene")


def prepare_work(cfg: DictConfig, scenes: int) -> Work:
    """``tracegs-prepare``: the 3DGS fits of each scene, then each clip's renders, caption, pseudo-target and
    latents."""
    prepare: PrepareConfig = OmegaConf.to_object(cfg.data.prepare)
    fit = cfg.data.prepare.fit
    steps = cfg.backbone.schedule.deploy_steps
    sparse = fit.iterations if prepare.student_final_fits else max(prepare.student_snapshots)
    per_scene = Work(fit_iterations=len(prepare.student_views) * sparse + len(prepare.dense_views) * fit.iterations)
    frames = prepare.frames_per_clip
    # A trajectory shared by every K has its teacher conditions (R_d among them) and its target encoded once, by
    # its first clip; otherwise each clip encodes all of its conditions and its target.
    shared_encodes = len(teacher_view_counts(prepare)) + 1 if prepare.shared_trajectories else 0
    for views in clip_views(cfg):
        conditions = len(clip_condition_keys(prepare, views))
        per_scene += Work(rendered_frames=conditions * frames, captions=1,
                          encodes=conditions + 1 - shared_encodes)
    per_scene += Work(encodes=shared_encodes).scaled(trajectory_count(prepare))
    if prepare.pseudo_target == "restorer":
        # One pseudo-target per trajectory: R_d's latent (encoded with the clip's conditions) denoised over the
        # M-step schedule, decoded (and, shared by several clips, captioned from R_d).
        restoration = Work(decodes=1, forwards=steps * guided(prepare.pseudo_target_guidance),
                           captions=int(prepare.shared_trajectories))
        per_scene += restoration.scaled(trajectory_count(prepare))
    return per_scene.scaled(scenes)


def train_work(cfg: DictConfig) -> Work:
    """``tracegs-train``: every rank's samples times the forwards each sample costs (Stage 1: both roles with
    gradient, Eq. supp-stage1; Stage 2: N student forwards with gradient and N teacher forwards without)."""
    exp, stage = cfg.experiment, cfg.stage.name
    samples_per_step = cfg.stage.batch_size * int(cfg.trainer.devices) * cfg.trainer.num_nodes
    if stage == Product.baseline:
        return Work(training_forwards=exp.baseline_steps * samples_per_step)
    if stage == Product.stage1:
        return Work(training_forwards=2 * exp.stage1_steps * samples_per_step)
    rollout = cfg.stage.rollout_steps * guided(cfg.stage.guidance_scale)
    return Work(training_forwards=exp.stage2_steps * samples_per_step * rollout,
                forwards=exp.stage2_steps * samples_per_step * rollout)


def evaluate_work(cfg: DictConfig, scenes: int) -> Work:
    """``tracegs-evaluate``: per scene and view count, the shared cold start, then per method the refinement
    (with N_r repair rounds of restored clips for a restorer)."""
    deploy, views = cfg.deploy, list(cfg.evaluation.views)
    steps = deploy.steps or cfg.backbone.schedule.deploy_steps
    after_cold = deploy.total_iters - deploy.repair_iters[0]
    work = Work()
    for k in views:
        work += Work(fit_iterations=deploy.repair_iters[0])
        for method in cfg.evaluation.methods:
            if method == "3dgs":
                work += Work(fit_iterations=after_cold)
                continue
            clips = len(deploy.repair_iters) * clips_per_round(deploy.trajectory, k, deploy.max_clips_per_round)
            work += Work(refine_iterations=after_cold, rendered_frames=clips * deploy.trajectory.frames_per_clip,
                         captions=clips, encodes=clips, decodes=clips,
                         forwards=clips * steps * guided(cfg.backbone.sampler.guidance_scale))
    return work.scaled(scenes)


def per_step_work(cfg: DictConfig, scenes: int) -> Work:
    """``report.kind=per_step`` (Fig. 6): per held-out clip, condition and variant, the rollout with the clean
    prediction decoded at every step, and the final restoration scored against the input."""
    prepare: PrepareConfig = OmegaConf.to_object(cfg.data.prepare)
    steps = cfg.backbone.schedule.deploy_steps
    clips = len(clip_views(cfg)) * scenes
    rollouts = clips * len(prepare.student_snapshots) * len(per_step_variants(ConfigTree.at(CONF_DIR)))
    forwards = steps * guided(cfg.backbone.sampler.guidance_scale)
    return Work(encodes=rollouts, forwards=2 * rollouts * forwards, decodes=rollouts * (steps + 1))


def test_scenes(cfg: DictConfig, dl3dv: int) -> int:
    """Benchmark scenes of the job's dataset: DL3DV-Benchmark's 28 (paper Sec. 4.2; its list is the user's), else
    the published list that ships with the configs."""
    if cfg.data.name == "dl3dv":
        return dl3dv
    return len(read_scene_list(cfg.data.source.test_list, "data.source.test_list"))


def plan(overrides: list[str], train_scenes: int, dl3dv_scenes: int) -> tuple[list[tuple[str, str, Work]], int]:
    """(label, command, work) of every command, in order, and how many variants train a Stage-2 student."""
    common = [*PAPER_JOB, *overrides]
    variants = table3_variants(ConfigTree.at(CONF_DIR))
    steps = [Step.of("prepare", "prepare DL3DV training cache (every teacher)").passing(common)]
    report = compose(config_name="report", overrides=common)
    others = [d for d in report.report.datasets if d != report.training_data]
    steps += sweep_steps([v.name for v in variants], [v.name for v in variants if v.train_stage2], common, others)
    steps += main_table_steps(report.report.main_datasets, report.training_data, swept=report.report.datasets,
                              user=common)
    rows = []
    for step in steps:
        work = Work()
        for job in step.jobs():
            cfg = compose(config_name=step.app, overrides=list(job.overrides))
            if step.app == "prepare":
                scenes = train_scenes if cfg.data.prepare.split == "train" else test_scenes(cfg, dl3dv_scenes)
                work += prepare_work(cfg, scenes)
            elif step.app == "train":
                work += train_work(cfg)
            elif step.app == "evaluate":
                work += evaluate_work(cfg, test_scenes(cfg, dl3dv_scenes))
            elif cfg.report.kind == "per_step":
                work += per_step_work(cfg, test_scenes(cfg, dl3dv_scenes))
        command = f"tracegs-{step.app} " + " ".join(step.overrides)
        rows.append((step.label, command, work))
    return rows, sum(v.train_stage2 for v in variants)


def scope_prepare_work(overrides: list[str], train_scenes: int) -> Work:
    """The training cache of the paper's own scope, one student (F): only the teacher F distils from
    (``variants_teachers``), so the sparse fits stop at their last student snapshot."""
    teachers = [override(key, value) for key, value in variants_teachers(table3_configs(ConfigTree.at(CONF_DIR), ["F"])).items()]
    cfg = compose(config_name="prepare", overrides=[*PAPER_JOB, *overrides, *teachers])
    return prepare_work(cfg, train_scenes)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train-scenes", type=int, default=112, help="DL3DV training scenes (paper Sec. 4.1: 112)")
    parser.add_argument("--dl3dv-test-scenes", type=int, default=28, help="DL3DV-Benchmark scenes (paper: 28)")
    parser.add_argument("--measured", type=Path, help="gpu_check.json (benchmarks/gpu_check.py): its measured "
                        "seconds replace the estimates")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every command")
    args = parser.parse_args(argv)
    unit, sources = UnitSeconds(), {f.name: "assumed (one A100)" for f in fields(UnitSeconds)}
    if args.measured is not None:
        try:
            unit, sources = UnitSeconds.measured(json.loads(args.measured.read_text()))
        except (OSError, ValueError, KeyError, TypeError) as error:
            sys.exit(f"--measured {args.measured}: not a readable gpu_check.json ({type(error).__name__}: {error})")
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        rows, students = plan(args.overrides, args.train_scenes, args.dl3dv_test_scenes)
        scope_prepare = scope_prepare_work(args.overrides, args.train_scenes)
    hours = {label: round(work.gpu_hours(unit), 1) for label, _, work in rows}
    for name, source in sources.items():
        print(f"{getattr(unit, name):10.3f}  {name}: {source}")
    print(f"{'GPU hours':>10}  command (counts from the config, seconds per unit as above)")
    for label, command, work in rows:
        print(f"{work.gpu_hours(unit):10.1f}  {label}: {command}")
    total = sum(hours.values())
    scope_prepare_hours = round(scope_prepare.gpu_hours(unit), 1)
    paper_scope = scope_prepare_hours + hours["train Stage 1"] + hours["train Stage 2"] / students
    print(f"{total:10.1f}  in all ({total / 24 / 4:.1f} days on four GPUs)")
    print(f"{scope_prepare_hours:10.1f}  prepare with F's teacher alone (data.prepare.dense_views=[null] "
          "data.prepare.student_final_fits=false)")
    print(f"{paper_scope:10.1f}  that preparation + Stage 1 + one student, against the paper's {PAPER_GPU_HOURS} "
          f"(about five days on four A100s); Stage 2's training forwards {sources['training_forward_factor']}")
    summary = {"gpu_hours": hours, "gpu_hours_total": round(total, 1), "gpu_hours_paper_scope": round(paper_scope, 1),
               "paper_gpu_hours": PAPER_GPU_HOURS, "unit_seconds": asdict(unit), "unit_sources": sources}
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
