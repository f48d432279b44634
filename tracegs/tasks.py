"""What each entry point does with a composed config: build the components its sections describe, run.

The console scripts in :mod:`tracegs.cli` stay one line each; the demo chains these same functions.
Config sections are turned into the owning package's dataclasses (``OmegaConf.to_object``), so every
component receives typed hyperparameters and never the whole Hydra tree.
"""

from __future__ import annotations

import hashlib
import logging
import resource
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger("tracegs")


def section(node: DictConfig) -> Any:
    """The dataclass instance behind a structured config node (interpolations resolved)."""
    return OmegaConf.to_object(node)


# ----------------------------------------------------------------------------------------- prepare
def prepare(cfg: DictConfig) -> Path:
    """Generate the synthetic benchmark if selected, then build the paired-clip cache (issue: data)."""
    from tracegs.data.prepare import run_prepare, validate_config
    from tracegs.restorer.build import build_backbone

    validate_config(section(cfg.data.prepare))  # before the backbone loads: bad settings cost nothing
    backbone = build_backbone(section(cfg.backbone))
    synthetic = section(cfg.data.synthetic) if cfg.data.source.preset == "synthetic" else None
    manifest = run_prepare(section(cfg.data.prepare), section(cfg.data.source), backbone, synthetic)
    log.info("paired-clip cache: %s", manifest)
    return manifest


# ------------------------------------------------------------------------------------------- train
def train(cfg: DictConfig) -> Path | None:
    """Train ``cfg.stage.name`` into ``cfg.run_dir``; variant A trains no Stage 2."""
    from tracegs.training.config import TrainConfig
    from tracegs.training.run import train_stage

    if cfg.stage.name == "stage2" and not cfg.ablation.train_stage2:
        log.info("ablation %s is the frozen baseline restorer: Stage 2 has nothing to train", cfg.ablation.name)
        return None
    if cfg.stage.name == "baseline" and cfg.experiment.baseline_steps == 0:
        # Paper scale: variant A is GSFixer's pretrained restorer, loaded where it is used; the sweep's first
        # command must pass on to Stage 1 rather than stop.
        log.info("experiment %s: variant A is the pretrained restorer %s; nothing to train", cfg.experiment.name,
                 cfg.backbone.transformer.pretrained_path)
        return None
    train_cfg = TrainConfig(
        stage=section(cfg.stage),
        optimizer=section(cfg.optimizer),
        loss=section(cfg.loss),
        teacher=section(cfg.teacher),
        policy=section(cfg.policy),
        trainer=section(cfg.trainer),
        backbone=section(cfg.backbone),
        data=section(cfg.data.datamodule),
        output_dir=cfg.run_dir,
    )
    product = train_stage(train_cfg)
    log.info("%s product: %s", cfg.stage.name, product)
    return product


# ---------------------------------------------------------------------------------------- restorers
def _digest(path: Path) -> str:
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    sha = hashlib.sha256()
    for file in files:
        sha.update(file.read_bytes())
    return sha.hexdigest()[:16]


def build_restorer(cfg: DictConfig, student_adapter: str | None):
    """The deployed restorer: variant A's weights, plus a student adapter (None = variant A itself)."""
    from tracegs.deploy.restorers import DiffusionRestorer
    from tracegs.restorer import adapters
    from tracegs.restorer.build import build_backbone
    from tracegs.restorer.sampler import RestorationPipeline

    backbone_cfg = section(cfg.backbone)
    baseline = cfg.artifacts.baseline_weights
    if baseline is not None:
        if not Path(baseline).is_dir():
            raise FileNotFoundError(
                f"artifacts.baseline_weights: no baseline restorer at {baseline} (run tracegs-train stage=baseline)"
            )
        backbone_cfg.transformer.pretrained_path = baseline
    identity = [f"base={_digest(Path(backbone_cfg.transformer.pretrained_path))}"
                if backbone_cfg.transformer.pretrained_path else "base=random-init"]
    backbone = build_backbone(backbone_cfg, device="cuda" if torch.cuda.is_available() else "cpu")
    adapter = None
    if student_adapter is not None:
        student = Path(student_adapter)
        if not student.is_file():
            raise FileNotFoundError(
                f"artifacts.student_adapter: no student adapter at {student} "
                f"(run tracegs-train stage=stage2 ablation={student.parent.name})"
            )
        adapter = "student"
        adapters.load_adapter(backbone.transformer, adapter, student, trainable=False)
        identity.append(f"student={_digest(student)}")
    pipeline = RestorationPipeline(backbone, adapter=adapter)
    return DiffusionRestorer(pipeline, batch=cfg.deploy.clip_batch, identity=" ".join(identity), steps=cfg.deploy.steps)


def build_restorers(cfg: DictConfig, methods: Sequence[str]) -> dict:
    """Method name -> restorer (None = plain 3DGS, no restoration)."""
    builders = {"3dgs": lambda: None, "baseline": lambda: build_restorer(cfg, None),
                "tracegs": lambda: build_restorer(cfg, cfg.artifacts.student_adapter)}
    return {m: builders[m]() for m in methods}


# ------------------------------------------------------------------------------------------- scenes
def test_scenes(cfg: DictConfig) -> list[str]:
    """The evaluation scenes: the synthetic benchmark's test seeds (generated if missing) or the dataset's."""
    from tracegs.data.colmap import list_scenes
    from tracegs.data.synthetic import benchmark_scene_names, generate_benchmark

    if cfg.evaluation.scenes is not None:
        return list(cfg.evaluation.scenes)
    if cfg.data.source.preset == "synthetic":
        synthetic = section(cfg.data.synthetic)
        generate_benchmark(synthetic)
        return benchmark_scene_names(synthetic, "test")
    return list_scenes(section(cfg.data.source), "test")


def ground_truth_renderer(cfg: DictConfig):
    """Renders ground truth at any pose where the scene is known (the synthetic benchmark), else None."""
    if cfg.data.source.preset != "synthetic":
        return None
    from tracegs.data.synthetic import render_ground_truth

    return render_ground_truth


# --------------------------------------------------------------------------------- deploy / evaluate
def evaluate(cfg: DictConfig) -> dict:
    """Deploy every method on the test scenes at each view count; write results.json (+ tables, media)."""
    from tracegs.deploy.evaluate import evaluate as run_evaluation
    from tracegs.splat.render import require_available

    require_available(cfg.data.prepare.fit.backend, "data.prepare.fit.backend")
    restorers = build_restorers(cfg, list(cfg.evaluation.methods))
    results = run_evaluation(
        section(cfg.evaluation),
        section(cfg.data.source),
        section(cfg.deploy),
        section(cfg.data.prepare.fit),
        restorers,
        scenes=test_scenes(cfg),
        gt_renderer=ground_truth_renderer(cfg),
    )
    if cfg.evaluation.held_out_cache is not None:
        held_out_quality(cfg, restorers)
    log.info("evaluation written to %s", cfg.evaluation.out_dir)
    return results


def held_out_quality(cfg: DictConfig, restorers: dict) -> Path:
    """Score each diffusion restorer against its input R_s on the held-out clips (eval/clips.py)."""
    from tracegs.eval.clips import clip_restoration_psnr
    from tracegs.eval.report import write_held_out_report

    pipelines = {method: r.pipeline for method, r in restorers.items() if r is not None}
    quality = clip_restoration_psnr(pipelines, cfg.evaluation.held_out_cache, seed=cfg.deploy.seed,
                                    progress=cfg.evaluation.progress)
    table = write_held_out_report(quality, cfg.evaluation.out_dir)
    log.info("held-out clip quality: %s", table)
    return table


def deploy(cfg: DictConfig) -> list[Path]:
    """Restore-refine each test scene at each view count with the selected restorer; save refined PLYs."""
    from tracegs.deploy.evaluate import deploy_scenes
    from tracegs.splat.render import require_available

    require_available(cfg.data.prepare.fit.backend, "data.prepare.fit.backend")
    method = "tracegs" if cfg.ablation.train_stage2 else "baseline"
    restorer = build_restorers(cfg, [method])[method]
    return deploy_scenes(section(cfg.evaluation), section(cfg.data.source), section(cfg.deploy),
                         section(cfg.data.prepare.fit), restorer, test_scenes(cfg), cfg.run_dir)


# ------------------------------------------------------------------------------------------- report
def report(cfg: DictConfig) -> Path:
    """Merge evaluation shards (main), prepare shards (prepare) or an ablation sweep (ablation)."""
    from tracegs.data.prepare import merge_manifests
    from tracegs.deploy.evaluate import merge_results
    from tracegs.eval.report import write_ablation_report

    kind = cfg.report.kind
    if kind == "per_step":
        return per_step_report(cfg)
    if kind == "prepare":
        return merge_manifests(cfg.data.prepare.cache_dir)
    if kind == "main":
        out = Path(cfg.evaluation.out_dir)
        merge_results(out, views=list(cfg.evaluation.views), methods=list(cfg.evaluation.methods))
        return out / "results.json"
    if kind == "ablation":
        inputs = list(cfg.report.inputs) or [str(Path(cfg.paths.experiment_dir) / "eval" / v)
                                             for v in ("A", "B", "C", "D", "E", "F-", "F")]
        table = write_ablation_report([Path(p) for p in inputs], Path(cfg.report.output_dir))
        print(table.read_text())
        return table
    raise ValueError(f"report.kind must be 'main', 'prepare', 'ablation' or 'per_step', got {kind!r}")


def compose_run(config_name: str, extra: Sequence[str]) -> DictConfig:
    """``conf/<config_name>.yaml`` with this run's command-line overrides and ``extra`` (which wins), validated."""
    from hydra import compose
    from hydra.core.hydra_config import HydraConfig

    from tracegs.config.validate import validate

    replaced = {override.split("=", 1)[0] for override in extra}
    user = [o for o in HydraConfig.get().overrides.task if o.split("=", 1)[0] not in replaced]
    cfg = compose(config_name=config_name, overrides=[*user, *extra])
    validate(cfg)
    return cfg


def per_step_report(cfg: DictConfig) -> Path:
    """Fig. 6 across variants (default on-policy F vs off-policy E, plus A) on the held-out clips."""
    from tracegs.eval.clips import held_out_per_step_curves
    from tracegs.eval.report import plot_per_step_quality
    from tracegs.io import write_json_atomic

    if cfg.evaluation.held_out_cache is None:
        raise ValueError("evaluation.held_out_cache: report.kind=per_step needs a prepared held-out cache "
                         "(tracegs-prepare data.prepare.split=test)")
    pipelines = {}
    for variant in list(cfg.report.inputs) or ["A", "E", "F"]:
        # Each variant's own config says which restorer stands for it and where its student adapter is.
        variant_cfg = compose_run("report", [f"ablation={variant}"])
        method = variant_cfg.ablation.method
        pipelines[variant] = build_restorers(variant_cfg, [method])[method].pipeline
    curves = held_out_per_step_curves(pipelines, cfg.evaluation.held_out_cache, seed=cfg.deploy.seed,
                                      progress=cfg.evaluation.progress)
    out = Path(cfg.report.output_dir)
    write_json_atomic(curves, out / "per_step_variants.json")
    figure = plot_per_step_quality(curves, out / "fig6_per_step_variants.png")
    for variant, curve in curves.items():
        print(f"{variant}: " + " ".join(f"{value:.2f}" for value in curve))
    return figure


# --------------------------------------------------------------------------------------------- demo
def peak_rss_gib() -> float:
    """Peak resident memory of this process and its finished children, in GiB (Linux: ru_maxrss in KiB)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    scale = 1024**3 if sys.platform == "darwin" else 1024**2
    return max(own, children) / scale


# The held-out cache: the benchmark's test scenes prepared like the training clips, read only by evaluation.
HELD_OUT_SPLIT = "data.prepare.split=test"
HELD_OUT_CACHE = "evaluation.held_out_cache=${data.prepare.cache_dir}"

DEMO_STEPS = (
    ("prepare", ()),
    ("prepare", (HELD_OUT_SPLIT,)),
    ("train", ("stage=baseline",)),
    ("train", ("stage=stage1",)),
    ("train", ("stage=stage2", "ablation=F")),
    ("evaluate", ("ablation=F", HELD_OUT_SPLIT, HELD_OUT_CACHE)),
)


def demo(cfg: DictConfig) -> Path:
    """The whole pipeline on the composed experiment: prepare -> A -> Stage 1 -> Stage 2 (F) -> evaluation."""
    import lightning

    from tracegs.eval.report import print_results_table
    from tracegs.io import write_json_atomic

    start = time.perf_counter()
    tasks = {"prepare": prepare, "train": train, "evaluate": evaluate}
    results: dict = {}
    held_out_table = None
    for index, (name, extra) in enumerate(DEMO_STEPS, 1):
        step_cfg = compose_run(name, extra)
        lightning.seed_everything(step_cfg.seed, workers=True, verbose=False)
        log.info("[demo %d/%d] %s %s", index, len(DEMO_STEPS), name, " ".join(extra))
        outcome = tasks[name](step_cfg)
        if name == "evaluate":
            results = outcome
            held_out_table = Path(step_cfg.evaluation.out_dir) / "held_out_clips.md"
    results["wall_s"] = round(time.perf_counter() - start, 1)
    results["peak_rss_gib"] = round(peak_rss_gib(), 3)
    out_dir = Path(cfg.run_dir)
    write_json_atomic(results, out_dir / "results.json")
    print_results_table(results)
    if held_out_table is not None:
        print("\nRestoration of held-out clips (is the output closer to ground truth than its input R_s?)\n")
        print(held_out_table.read_text())
    print(f"\ntracegs-demo: finished in {results['wall_s']:.0f} s, peak RSS {results['peak_rss_gib']:.2f} GiB")
    print(f"tracegs-demo: all outputs under {Path(cfg.paths.experiment_dir).resolve()}")
    print(f"tracegs-demo: results table in {out_dir.resolve() / 'results.json'}")
    return out_dir
