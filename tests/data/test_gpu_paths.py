"""3DGS on the configured device: fitting, prepare and deployment through gsplat on CUDA (``gpu`` tests,
skipped without a GPU), and ``backend: gsplat`` without CUDA refused before any work."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
from scene_builders import tiny_configs

from tracegs.data.colmap import load_scene
from tracegs.data.config import SceneSourceConfig
from tracegs.data.preparation.driver import run_prepare
from tracegs.data.synthetic import benchmark_scene_names, generate_benchmark, ground_truth_model
from tracegs.deploy.config import EvaluationConfig, RefinementConfig
from tracegs.deploy.restorers import GroundTruthRestorer
from tracegs.deploy.scenes import deploy_scenes
from tracegs.eval.scoring import score_units
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig
from tracegs.splat.config import GaussianFitConfig, TrajectoryConfig
from tracegs.splat.fit import GaussianFitter, View, fit_gaussians
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.render import gsplat_available

gpu = pytest.mark.gpu
needs_cuda = pytest.mark.skipif(not gsplat_available(), reason="needs CUDA and gsplat")


@pytest.mark.skipif(gsplat_available(), reason="checks the refusal on a machine without CUDA")
@pytest.mark.parametrize("stage", ["evaluate", "deploy", "fit"])
def test_gsplat_without_cuda_is_refused_before_any_work(stage, tmp_path):
    fit = GaussianFitConfig(backend="gsplat")
    out = tmp_path / "out"
    source = SceneSourceConfig(root=str(tmp_path / "no_such_root"))
    cfg = EvaluationConfig(out_dir=str(out), views=[3], progress=False)
    run = {
        "evaluate": lambda: score_units(cfg, source, RefinementConfig(), fit, {"3dgs": None}, scenes=["x"]),
        "deploy": lambda: deploy_scenes(cfg, source, RefinementConfig(), fit, None, ["x"], out),
        "fit": lambda: GaussianFitter(GaussianModel.random(10), fit, 1.0),
    }[stage]
    with pytest.raises(ValueError, match=r"fit\.backend='gsplat' needs CUDA"):
        run()
    assert not out.exists()


def _gsplat(fit: GaussianFitConfig) -> GaussianFitConfig:
    return replace(fit, backend="gsplat")


def _first_scene(tmp_path):
    synthetic, source, prepare = tiny_configs(tmp_path)
    generate_benchmark(synthetic, progress=False)
    return synthetic, source, prepare, load_scene(source, benchmark_scene_names(synthetic, "train")[0])


@gpu
@needs_cuda
def test_fit_runs_through_gsplat_on_cuda(tmp_path):
    _, _, prepare, scene = _first_scene(tmp_path)
    views = [View(image=scene.load_image(i), camera=scene.cameras[i]) for i in range(0, len(scene), 3)]
    model = fit_gaussians(views, _gsplat(prepare.fit), progress=False)[prepare.fit.iterations]
    assert model.means.device.type == "cuda"


@gpu
@needs_cuda
def test_prepare_runs_through_gsplat_with_the_backbone_on_cuda(tmp_path):
    synthetic, source, prepare = tiny_configs(tmp_path)
    manifest = run_prepare(replace(prepare, fit=_gsplat(prepare.fit)), source,
                           build_backbone(BackboneConfig(), device="cuda"), synthetic, progress=False)
    assert json.loads(manifest.read_text())["scenes"]


@gpu
@needs_cuda
def test_deployment_runs_through_gsplat_on_cuda(tmp_path):
    _, source, prepare, scene = _first_scene(tmp_path)
    oracle = GroundTruthRestorer(ground_truth_model(scene).to("cuda"))
    refine_cfg = RefinementConfig(total_iters=40, repair_iters=[10, 25], max_clips_per_round=1,
                                  trajectory=TrajectoryConfig(frames_per_clip=5, ellipse_frames=24))
    cfg = EvaluationConfig(views=[3], progress=False)
    (path,) = deploy_scenes(cfg, source, refine_cfg, _gsplat(prepare.fit), oracle, [scene.name], tmp_path / "out")
    assert path.is_file()
