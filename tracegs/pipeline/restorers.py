"""The restorers and scenes a deployment run works on, from its config."""

from __future__ import annotations

from collections.abc import Sequence

from omegaconf import DictConfig

from tracegs.console import show
from tracegs.data.colmap import list_scenes, require_held_out, training_scenes
from tracegs.data.synthetic import benchmark_scene_names, generate_benchmark, render_ground_truth
from tracegs.deploy.assembly import RestorerArtifacts, restorer_holdings
from tracegs.deploy.assembly import build_restorers as assemble
from tracegs.pipeline.upstream import locate_artifacts, section
from tracegs.restorer.memory import holdings_table, loads_pretrained_components


def restorers_for_run(cfg: DictConfig, methods: Sequence[str]) -> dict:
    """Method name -> restorer (None = plain 3DGS), the diffusion methods on one backbone (deploy/assembly.py)."""
    locate_artifacts(cfg, ["baseline_weights", "student_adapter"])
    backbone = section(cfg.backbone)
    if loads_pretrained_components(backbone):
        show(holdings_table(restorer_holdings(backbone, methods, cfg.deploy.captions.blip2_path)))
    artifacts = RestorerArtifacts(baseline_weights=cfg.artifacts.baseline_weights,
                                  student_adapter=cfg.artifacts.student_adapter, ablation=cfg.ablation.name)
    return assemble(backbone, artifacts, methods, batch=cfg.deploy.clip_batch, steps=cfg.deploy.steps)


def test_scenes(cfg: DictConfig) -> list[str]:
    """The evaluation scenes, worked out once per run: ``evaluation.scenes`` (refused if the restorer trains on
    one), else the synthetic benchmark's test seeds (generated if missing) or the dataset's test list."""
    if cfg.evaluation.scenes is not None:
        training = (benchmark_scene_names(section(cfg.data.synthetic), "train") if cfg.data.source.preset == "synthetic"
                    else training_scenes(section(cfg.data.source)))
        require_held_out(list(cfg.evaluation.scenes), training, "evaluation.scenes")
        return list(cfg.evaluation.scenes)
    if cfg.data.source.preset == "synthetic":
        synthetic = section(cfg.data.synthetic)
        generate_benchmark(synthetic, splits=("test",))
        return benchmark_scene_names(synthetic, "test")
    return list_scenes(section(cfg.data.source), "test")


def ground_truth_renderer(cfg: DictConfig):
    """Renders ground truth at any pose where the scene is known (the synthetic benchmark), else None."""
    return render_ground_truth if cfg.data.source.preset == "synthetic" else None
