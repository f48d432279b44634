"""One render path and one trajectory rule for clips: prepare's conditions and deployment's clips are the same
images along the same cameras."""

from __future__ import annotations

import pytest
import torch

from tracegs.data.config import PrepareConfig, SceneSourceConfig
from tracegs.data.preparation.plan import clip_cameras, plan_scene, trajectory_seed
from tracegs.data.preparation.renders import render_conditions
from tracegs.deploy.config import RefinementConfig
from tracegs.deploy.refine import render_round_clips
from tracegs.splat.config import GaussianFitConfig, TrajectoryConfig
from tracegs.splat.fit import GaussianFitter, View
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.ply import save_ply
from tracegs.splat.trajectory import round_clips


@pytest.mark.parametrize("captured_ends", [False, True])
def test_prepare_and_deployment_render_one_clip_identically(colmap_scene, tmp_path, captured_ends):
    """A snapshot at iteration 340 (SH degree 3 by then, view-dependent colour present, a grey background)
    rendered along deployment's clips by deployment and, from its PLY, by prepare: identical frames, the captured
    reference images at both ends included where ``trajectory.captured_ends``."""
    root, _ = colmap_scene
    source = SceneSourceConfig(root=str(root.parent), preset="custom")
    fit = GaussianFitConfig(background=[0.2, 0.4, 0.6])
    trajectory = TrajectoryConfig(frames_per_clip=5, captured_ends=captured_ends)
    prepare = PrepareConfig(student_views=[3], dense_views=[6], pseudo_target="dense", fit=fit,
                            frames_per_clip=5, trajectory=trajectory)
    plan = plan_scene(source, prepare, root.name)
    generator = torch.Generator().manual_seed(0)
    model = GaussianModel.random(400, radius=1.0, generator=generator)
    with torch.no_grad():
        model.sh_rest.copy_(0.3 * torch.randn(model.sh_rest.shape, generator=generator))
    fitter = GaussianFitter(model, fit, scene_extent=1.0)
    fitter.iteration = 340
    views = plan.split.views(3)
    captured = [View(image=plan.scene.load_image(i), camera=plan.scene.cameras[i]) for i in views]
    refinement = RefinementConfig(trajectory=trajectory)
    clips = render_round_clips(fitter, captured, 0, refinement, fit, "", torch.Generator().manual_seed(0))
    pairs = [pair for pair, _ in round_clips([v.camera for v in captured], 0, trajectory, refinement.max_clips_per_round,
                                            torch.Generator().manual_seed(0))]
    snapshot = tmp_path / "it000340.ply"
    save_ply(model, snapshot)
    for clip, (a, b) in zip(clips, pairs, strict=True):
        conditions, ground_truth = render_conditions(plan, clip.cameras, {"s3_it340": (snapshot, 340)}, prepare,
                                                     [views[a], views[b]])
        assert ground_truth is None
        assert torch.equal(conditions["s3_it340"], clip.frames)
        assert torch.equal(clip.frames[0], captured[a].image) == captured_ends


def test_a_six_view_training_clip_follows_deployment_from_those_six_views(colmap_scene):
    """Prepare's clips of K = 6 and deployment's round 0 from the same six captured views, with the same seed
    stream: identical cameras, clip for clip (the ellipse and references are the 6-view set's, not the 3-view
    set's); and the scene's clips are divided evenly among K = 3, 6, 9."""
    root, _ = colmap_scene
    source = SceneSourceConfig(root=str(root.parent), preset="custom")
    fit = GaussianFitConfig()
    trajectory = TrajectoryConfig(frames_per_clip=5)
    prepare = PrepareConfig(student_views=[3, 6, 9], dense_views=[None], pseudo_target="dense", fit=fit,
                            clips_per_scene=19, frames_per_clip=5, trajectory=trajectory)
    plan = plan_scene(source, prepare, root.name)
    clips = clip_cameras(plan, prepare)
    counts = sorted([c["views"] for c in clips].count(k) for k in (3, 6, 9))
    assert counts == [6, 6, 7]
    six = [clip for clip in clips if clip["views"] == 6][:6]  # round 0 of six views has six clips
    views = plan.split.views(6)
    captured = [View(image=plan.scene.load_image(i), camera=plan.scene.cameras[i]) for i in views]
    fitter = GaussianFitter(GaussianModel.random(50, radius=1.0, generator=torch.Generator().manual_seed(0)), fit,
                            scene_extent=1.0)
    generator = torch.Generator().manual_seed(trajectory_seed(prepare, root.name, 6))
    refinement = RefinementConfig(trajectory=trajectory, max_clips_per_round=None)
    deployed = render_round_clips(fitter, captured, 0, refinement, fit, "", generator)
    assert len(deployed) == len(six) == 6
    assert {i for clip in six for i in clip["refs"]} == set(views)
    for training, deployment in zip(six, deployed):
        assert len(training["cameras"]) == len(deployment.cameras) == 5
        for ours, theirs in zip(training["cameras"], deployment.cameras):
            assert torch.equal(ours.world_to_camera, theirs.world_to_camera) and torch.equal(ours.K, theirs.K)
        assert torch.equal(deployment.references[0], plan.scene.load_image(training["refs"][0]))


def test_a_larger_cache_begins_with_the_smaller_caches_clips(colmap_scene):
    """A clip's K and trajectory are drawn per scene and clip index, so preparing more clips per scene appends
    clips: the first 8 of 32 are the 8 (what lets A and Stage 1 read the first clips of Stage 2's larger cache,
    experiment.baseline_clips_per_scene)."""
    root, _ = colmap_scene
    source = SceneSourceConfig(root=str(root.parent), preset="custom")
    trajectory = TrajectoryConfig(frames_per_clip=5)

    def cameras(clips_per_scene: int) -> list[dict]:
        prepare = PrepareConfig(student_views=[3, 6, 9], dense_views=[None], pseudo_target="dense",
                                clips_per_scene=clips_per_scene, frames_per_clip=5, trajectory=trajectory)
        return clip_cameras(plan_scene(source, prepare, root.name), prepare)

    few, many = cameras(8), cameras(32)
    assert len(many) == 32
    for small, large in zip(few, many[:8], strict=True):
        assert (small["views"], small["refs"], small["trajectory"]) == (large["views"], large["refs"], large["trajectory"])
        assert all(torch.equal(a.world_to_camera, b.world_to_camera) for a, b in zip(small["cameras"], large["cameras"]))
