"""Restore-refine loop (supplement A.5): w_reg schedule, pseudo-set replacement, captured-view weight,
pose bookkeeping, and that a repair round helps on held-out views.

The "restorer" in these tests is ``GroundTruthRestorer``: a real component implementing the restorer
interface that returns ground-truth renders of the known tiny scene at the poses it is given (an oracle),
so the loop's plumbing is tested independently of how good a trained diffusion restorer is.
"""

import math

import pytest
import torch

from tracegs.deploy.config import RefinementConfig
from tracegs.deploy.refine import cold_start, pseudo_weight, refine
from tracegs.deploy.restorers import GroundTruthRestorer
from tracegs.splat.cameras import Camera
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.fit import GaussianFitter, View
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.render import render_views
from tracegs.splat.trajectory import TrajectoryConfig


def test_w_reg_half_sine_values():
    first, total = 7000, 30000  # the paper's schedule
    assert pseudo_weight(0, first, total) == 0.0
    assert pseudo_weight(first - 1, first, total) == 0.0
    assert pseudo_weight(first, first, total) == 0.0
    assert pseudo_weight((first + total) // 2, first, total) == pytest.approx(1.0)
    assert pseudo_weight(total, first, total) == 0.0
    quarter = first + (total - first) // 4
    assert pseudo_weight(quarter, first, total) == pytest.approx(math.sin(math.pi / 4), abs=1e-4)
    # one global half-sine: not restarted at the later repairs (17000, 27000), symmetric about the midpoint
    assert pseudo_weight(17000, first, total) == pytest.approx(pseudo_weight(20000, first, total))
    assert pseudo_weight(27000, first, total) < pseudo_weight(17000, first, total)
    assert pseudo_weight(18500, first, total, lambda_reg=0.5) == pytest.approx(0.5)
    with pytest.raises(ValueError):
        pseudo_weight(10, 0, 100)


# ---------------------------------------------------------------- a tiny known scene

H, W = 24, 36


def _ring(n: int, radius: float = 2.6, height: float = 0.6) -> list[Camera]:
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = torch.tensor([radius * math.cos(a), radius * math.sin(a), height])
        cams.append(Camera.look_at(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]), fov_x_deg=60.0,
                                   width=W, height=H))
    return cams


@pytest.fixture(scope="module")
def tiny_scene():
    g = torch.Generator().manual_seed(0)
    gt = GaussianModel.random(220, radius=0.8, generator=g, initial_opacity=0.9)
    with torch.no_grad():
        gt.log_scales.fill_(math.log(0.09))
    cams = _ring(16)
    background = torch.zeros(3)
    images = render_views(gt, cams, background, 0)
    # Three captured views spread around the ring, held-out views between them: only pseudo-observations
    # (each clip follows the ellipse the shorter way between two captured views) show the refinement
    # what the scene looks like from there.
    captured_ids = [0, 5, 10]
    held_out = [3, 8, 13]
    captured = [View(image=images[i], camera=cams[i]) for i in captured_ids]
    init = GaussianModel.random(300, radius=0.9, generator=torch.Generator().manual_seed(1))
    return gt, cams, images, captured, held_out, init


def _configs():
    fit_cfg = GaussianFitConfig(iterations=80, snapshot_iters=[], seed=0)
    refine_cfg = RefinementConfig(total_iters=80, repair_iters=[20, 50], lambda_reg=1.0,
                                  trajectory=TrajectoryConfig(frames_per_clip=9, ellipse_frames=32),
                                  max_clips_per_round=None, seed=3)
    return fit_cfg, refine_cfg


class _SpyTrainUntil:
    """Records what the loop hands to the (real) fitter at each call, then calls through."""

    def __init__(self):
        self.calls = []
        self._original = GaussianFitter.train_until

    def __call__(self, fitter, until, captured, pseudo=(), pseudo_weight=None, **kwargs):
        self.calls.append({"start": fitter.iteration, "until": until, "captured": list(captured),
                           "pseudo": list(pseudo), "weight": pseudo_weight})
        return self._original(fitter, until, captured, pseudo=pseudo, pseudo_weight=pseudo_weight, **kwargs)


def _held_out_l1(model, scene) -> float:
    gt, cams, images, _, held_out, _ = scene
    renders = render_views(model, [cams[i] for i in held_out], torch.zeros(3), None)
    return float((renders - images[held_out]).abs().mean())


def test_repair_rounds_replace_pseudo_set_keep_poses_and_help(tiny_scene, monkeypatch):
    gt, cams, images, captured, held_out, init = tiny_scene
    fit_cfg, refine_cfg = _configs()
    cold = cold_start(captured, init, refine_cfg, fit_cfg)
    assert cold.iteration == refine_cfg.repair_iters[0]

    plain = refine(cold, captured, None, refine_cfg, fit_cfg)
    assert cold.iteration == refine_cfg.repair_iters[0]  # the cold start is branched, not consumed

    spy = _SpyTrainUntil()
    monkeypatch.setattr(GaussianFitter, "train_until", lambda self, *a, **k: spy(self, *a, **k))
    rounds = []
    oracle = GroundTruthRestorer(gt)
    repaired = refine(cold, captured, oracle, refine_cfg, fit_cfg, on_round=rounds.append)

    # one repair per repair iteration, each followed by one optimisation segment up to the next / J
    assert [r.iteration for r in rounds] == refine_cfg.repair_iters
    assert [(c["start"], c["until"]) for c in spy.calls] == [(20, 50), (50, 80)]
    for call, rnd in zip(spy.calls, rounds):
        # the pseudo-set is exactly this round's restorations: replaced, never accumulated
        assert len(rnd.pseudo) > 0
        assert len(call["pseudo"]) == len(rnd.pseudo)
        assert all(a is b for a, b in zip(call["pseudo"], rnd.pseudo))
        # captured views stay active with unit weight: the same views and images every segment,
        # while only the pseudo term is scaled by w_reg(j)
        assert [v.camera for v in call["captured"]] == [v.camera for v in captured]
        assert all(torch.equal(a.image, b.image) for a, b in zip(call["captured"], captured))
        for j in (call["start"], (call["start"] + call["until"]) // 2, call["until"]):
            assert call["weight"](j) == pytest.approx(pseudo_weight(j, 20, 80))
    first_poses = {tuple(v.camera.center.tolist()) for v in rounds[0].pseudo}
    second_poses = {tuple(v.camera.center.tolist()) for v in rounds[1].pseudo}
    assert first_poses.isdisjoint(second_poses)  # the trajectory is resampled each round

    # every restored frame keeps the pose it was rendered at (and is the oracle's image of that pose)
    for rnd in rounds:
        targets = [(frame_cam, clip) for clip in rnd.clips for frame_cam in clip.cameras[1:-1]]
        assert len(targets) == len(rnd.pseudo)
        for view, (cam, _) in zip(rnd.pseudo, targets):
            assert view.camera is cam
        sample = rnd.pseudo[len(rnd.pseudo) // 2]
        truth = render_views(gt, [sample.camera], torch.zeros(3), 0)[0]
        assert torch.allclose(sample.image, truth, atol=1e-5)
        # clip ends sit at captured (reference) views, and the references are those captured images
        for clip in rnd.clips:
            ends = [min(range(len(captured)), key=lambda i: float((captured[i].camera.center - c.center).norm()))
                    for c in (clip.cameras[0], clip.cameras[-1])]
            assert torch.equal(clip.references[0], captured[ends[0]].image)
            assert torch.equal(clip.references[1], captured[ends[1]].image)

    # repairing with correct restorations lowers the loss on held-out views vs. no repair
    loss_plain, loss_repaired = _held_out_l1(plain, tiny_scene), _held_out_l1(repaired, tiny_scene)
    assert loss_repaired < 0.95 * loss_plain  # measured 0.937 with views between the captured ones
