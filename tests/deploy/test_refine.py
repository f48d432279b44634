"""Restore-refine loop (supplement A.5): w_reg schedule, pseudo-set replacement, captured-view weight,
pose bookkeeping, and that a repair round helps on held-out views.

The "restorer" in these tests is ``GroundTruthRestorer``: a real component implementing the restorer
interface that returns ground-truth renders of the known tiny scene at the poses it is given (an oracle),
so the loop's plumbing is tested independently of how good a trained diffusion restorer is.
"""

import math

import pytest
import torch

from tracegs.deploy.config import KeptFrames, RefinementConfig
from tracegs.deploy.refine import cold_start, pseudo_weight, refine, repair_round
from tracegs.deploy.restorers import GroundTruthRestorer
from tracegs.splat.cameras import Camera
from tracegs.splat.config import DensificationConfig, GaussianFitConfig, PseudoSsim
from tracegs.splat.fit import GaussianFitter, View, mean_ssim
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


# ---------------------------------------------------------------- GSFixer's release against the corrected protocol


@pytest.mark.parametrize("kept, ends_kept", [(KeptFrames.every, True), (KeptFrames.between_ends, False)])
def test_kept_frames_are_every_restored_frame_as_released_or_those_between_the_ends(tiny_scene, kept, ends_kept):
    """gsfixer/extrapolation/outpaint/base.py l. 129-140: every restored frame of a clip, at the camera it was
    rendered at, the clip's two captured-view ends included; corrected: frames[1:-1]."""
    gt, _, _, captured, _, init = tiny_scene
    fit_cfg, refine_cfg = _configs()
    refine_cfg.kept_frames = kept
    cold = cold_start(captured, init, refine_cfg, fit_cfg)
    rnd = repair_round(cold, captured, GroundTruthRestorer(gt), 0, refine_cfg, fit_cfg, "", torch.Generator())
    cameras = [c for clip in rnd.clips for c in (clip.cameras if ends_kept else clip.cameras[1:-1])]
    assert [view.camera for view in rnd.pseudo] == cameras
    assert len(rnd.pseudo) == len(rnd.clips) * (9 if ends_kept else 7)


def _fitter(tiny_scene, **fit) -> tuple[GaussianFitter, View, View]:
    gt, cams, images, captured, held_out, init = tiny_scene
    cfg = GaussianFitConfig(iterations=80, snapshot_iters=[], seed=0, **fit,
                            densification=DensificationConfig(refine_start_iter=1000, refine_stop_iter=2000))
    fitter = GaussianFitter(init.clone(), cfg, 3.0)
    # A pseudo view whose image is off the scene: its own SSIM differs from the captured pair's.
    pseudo = View(image=images[held_out[0]].flip(-1), camera=cams[held_out[0]])
    return fitter, captured[0], pseudo


@pytest.mark.parametrize("pair", [PseudoSsim.captured, PseudoSsim.pseudo])
def test_the_pseudo_term_uses_the_ssim_pair_its_protocol_names(tiny_scene, pair):
    """train.py l. 210-213: 0.8 L1(pseudo render, restored frame) + 0.2 (1 - SSIM(captured render, captured
    image)); corrected: the pseudo view's own D-SSIM."""
    fitter, captured, pseudo = _fitter(tiny_scene, pseudo_ssim=pair)
    with torch.no_grad():
        loss, pseudo_loss, _ = fitter._losses(captured, pseudo, 0)
        (c_render, c_image, _), (p_render, p_image, _) = fitter._render(captured, 0), fitter._render(pseudo, 0)
    ssim_view = (c_render, c_image) if pair == PseudoSsim.captured else (p_render, p_image)
    expected = 0.8 * (p_render - p_image).abs().mean() + 0.2 * (1 - mean_ssim(*ssim_view))
    assert pseudo_loss.item() == pytest.approx(expected.item(), rel=1e-5)
    other = (p_render, p_image) if pair == PseudoSsim.captured else (c_render, c_image)
    assert abs(pseudo_loss.item() - (0.8 * (p_render - p_image).abs().mean() + 0.2 * (1 - mean_ssim(*other))).item()) > 1e-3
    assert loss.item() == pytest.approx((0.8 * (c_render - c_image).abs().mean()
                                         + 0.2 * (1 - mean_ssim(c_render, c_image))).item(), rel=1e-5)


@pytest.mark.parametrize("pseudo_densification", [False, True])
def test_densification_counts_the_captured_views_gradients_only_as_released(tiny_scene, pseudo_densification):
    """train.py l. 198-202 and 243: the densification statistics of a step with a pseudo view come from the
    captured view's render alone; corrected: from both renders."""
    fitter, captured, pseudo = _fitter(tiny_scene, pseudo_densification=pseudo_densification)
    with torch.no_grad():
        seen = [(fitter._render(view, 0)[2]["radii"] > 0).reshape(len(fitter.model), -1).any(-1)
                for view in (captured, pseudo)]
    fitter.step([captured], [pseudo], lambda j: 1.0)
    expected = seen[0].float() + (seen[1].float() if pseudo_densification else 0.0)
    assert torch.equal(fitter.strategy_state["count"], expected)


def test_screen_pruning_removes_gaussians_wider_than_20_px_after_the_first_reset(tiny_scene):
    """train.py l. 246 (the reference optimiser's rule): after the first opacity reset, a densification step drops
    Gaussians whose screen radius exceeded 20 px; before it, and without ``screen_prune_px``, none."""
    gt, cams, images, captured, _, init = tiny_scene
    model = init.clone()
    with torch.no_grad():
        model.log_scales[:5] = math.log(1.5)  # five Gaussians wider than the 36-px image
    def pruned_at(step: int, px: float | None) -> int:
        cfg = GaussianFitConfig(iterations=80, snapshot_iters=[], seed=0, densification=DensificationConfig(
            refine_start_iter=0, refine_stop_iter=1000, refine_every=step, reset_every=10, grow_grad2d=1e9,
            prune_opa=0.0, prune_scale3d=1e9, screen_prune_px=px, max_gaussians=None))
        fitter = GaussianFitter(model.clone(), cfg, 3.0)
        fitter.iteration = step
        fitter.step(captured, (), None)
        return len(model) - len(fitter.model)
    assert pruned_at(11, 20.0) >= 5
    assert pruned_at(11, None) == 0
    assert pruned_at(5, 20.0) == 0
