"""One render path for clips: prepare's conditions and deployment's clips are the same images."""

from __future__ import annotations

import torch

from tracegs.data.config import PrepareConfig, SceneSourceConfig
from tracegs.data.prepare import plan_scene, render_conditions
from tracegs.deploy.config import RefinementConfig
from tracegs.deploy.refine import render_round_clips
from tracegs.splat.config import GaussianFitConfig, TrajectoryConfig
from tracegs.splat.fit import GaussianFitter, View
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.ply import save_ply


def test_prepare_and_deployment_render_one_clip_identically(colmap_scene, tmp_path):
    """A snapshot at iteration 340 (SH degree 3 by then, view-dependent colour present, a grey background)
    rendered along deployment's clips by deployment and, from its PLY, by prepare: identical frames."""
    root, _ = colmap_scene
    source = SceneSourceConfig(root=str(root.parent), preset="custom")
    fit = GaussianFitConfig(background=[0.2, 0.4, 0.6])
    trajectory = TrajectoryConfig(frames_per_clip=5)
    prepare = PrepareConfig(student_views=[3], dense_views=[6], pseudo_target="dense", fit=fit,
                            frames_per_clip=5, trajectory=trajectory)
    plan = plan_scene(source, prepare, root.name)
    generator = torch.Generator().manual_seed(0)
    model = GaussianModel.random(400, radius=1.0, generator=generator)
    with torch.no_grad():
        model.sh_rest.copy_(0.3 * torch.randn(model.sh_rest.shape, generator=generator))
    fitter = GaussianFitter(model, fit, scene_extent=1.0)
    fitter.iteration = 340
    captured = [View(image=plan.scene.load_image(i), camera=plan.scene.cameras[i]) for i in plan.split.views(3)]
    clips = render_round_clips(fitter, captured, 0, RefinementConfig(trajectory=trajectory), fit, "",
                               torch.Generator().manual_seed(0))
    snapshot = tmp_path / "it000340.ply"
    save_ply(model, snapshot)
    for clip in clips:
        conditions, ground_truth = render_conditions(plan, clip.cameras, {"s3_it340": (snapshot, 340)}, prepare)
        assert ground_truth is None
        assert torch.equal(conditions["s3_it340"], clip.frames)
