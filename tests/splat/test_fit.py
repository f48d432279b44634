"""3DGS optimiser: fitting quality with densification, pseudo-observation hook, snapshots, branching."""

from __future__ import annotations

import copy

import pytest
import torch
from gsplat.strategy import DefaultStrategy
from support.scenes import psnr, random_scene, ring_cameras

from tracegs.splat.config import DensificationConfig, GaussianFitConfig
from tracegs.splat.fit import GaussianFitter, View, camera_extent, fit_gaussians, mean_ssim, photometric_loss
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.render import render

FIT_PSNR_DB = 30.0  # training-view PSNR the fitting test demands


def sphere_scene(n: int, seed: int = 0) -> tuple[GaussianModel, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator), dim=1)
    return GaussianModel.from_points(directions, torch.rand(n, 3, generator=generator), initial_opacity=0.95), \
        directions


def test_fits_known_scene_from_noisy_init_with_growth_and_pruning(monkeypatch):
    truth, points = sphere_scene(400)
    cameras = ring_cameras(24)
    with torch.no_grad():
        views = [View(render(truth, camera).image.clamp(0, 1), camera) for camera in cameras]
    generator = torch.Generator().manual_seed(1)
    picks = torch.randint(0, len(points), (200,), generator=generator)
    noisy = points[picks] + 0.05 * torch.randn(200, 3, generator=generator)
    init = GaussianModel.from_points(noisy, torch.rand(200, 3, generator=generator))
    # Transparent junk that densification must prune.
    junk = GaussianModel.from_points(torch.randn(50, 3, generator=generator), torch.rand(50, 3, generator=generator),
                                     initial_opacity=0.002)
    init = GaussianModel(*(torch.cat([getattr(init, n), getattr(junk, n)]) for n in
                           ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")))

    events = {"grown": 0, "pruned": 0}
    grow, prune = DefaultStrategy._grow_gs, DefaultStrategy._prune_gs

    def counting_grow(self, *args, **kwargs):
        duplicated, split = grow(self, *args, **kwargs)
        events["grown"] += duplicated + split
        return duplicated, split

    def counting_prune(self, *args, **kwargs):
        pruned = prune(self, *args, **kwargs)
        events["pruned"] += pruned
        return pruned

    monkeypatch.setattr(DefaultStrategy, "_grow_gs", counting_grow)
    monkeypatch.setattr(DefaultStrategy, "_prune_gs", counting_prune)
    cfg = GaussianFitConfig(iterations=500, snapshot_iters=[500], densification=DensificationConfig(
        refine_start_iter=30, refine_every=20, refine_stop_iter=350, reset_every=150, grow_grad2d=0.003))
    fitter = GaussianFitter(init, cfg, camera_extent(cameras))
    fitter.train_until(500, views, progress=False)

    with torch.no_grad():
        scores = [psnr(render(fitter.model, view.camera).image, view.image) for view in views]
    assert sum(scores) / len(scores) >= FIT_PSNR_DB, f"training-view PSNR {sum(scores) / len(scores):.2f} dB"
    assert events["grown"] > 0 and events["pruned"] >= 50
    assert len(fitter.model) > 200


def small_problem(n_views: int = 4):
    truth = random_scene(60, seed=7)
    cameras = ring_cameras(n_views)
    with torch.no_grad():
        views = [View(render(truth, camera).image.clamp(0, 1), camera) for camera in cameras]
    cfg = GaussianFitConfig(iterations=12, snapshot_iters=[4, 8, 12], sh_degree_interval=4,
                            densification=DensificationConfig(refine_start_iter=2, refine_every=3,
                                                              refine_stop_iter=10, reset_every=6))
    return views, cfg, random_scene(80, seed=8)


def test_fit_gaussians_returns_independent_snapshots():
    views, cfg, init = small_problem()
    snapshots = fit_gaussians(views, cfg, init)
    assert sorted(snapshots) == [4, 8, 12]
    assert not torch.equal(snapshots[4].means, snapshots[12].means)
    assert snapshots[4].means.data_ptr() != snapshots[8].means.data_ptr()
    assert torch.equal(init.means, random_scene(80, seed=8).means)  # the initial model is not modified


def test_pseudo_term_follows_weight_schedule_and_zero_weight_is_inert():
    views, cfg, init = small_problem()
    captured, pseudo = views[:1], views[1:]
    seen = []

    def weight(j: int) -> float:
        seen.append(j)
        return 0.0

    base = GaussianFitter(init.clone(), cfg, 3.0)
    base.train_until(6, captured, progress=False)
    zero = GaussianFitter(init.clone(), cfg, 3.0)
    zero.train_until(6, captured, pseudo, pseudo_weight=weight, progress=False)
    assert seen == list(range(6))
    for a, b in zip(base.model.parameters(), zero.model.parameters()):
        assert torch.allclose(a, b, atol=1e-5)  # multi-threaded reductions may differ in the last bits
    weighted = GaussianFitter(init.clone(), cfg, 3.0)
    weighted.train_until(6, captured, pseudo, pseudo_weight=lambda j: 1.0, progress=False)
    assert not torch.equal(weighted.model.means, base.model.means)


def test_deepcopied_fitter_continues_identically_and_independently():
    views, cfg, init = small_problem()
    fitter = GaussianFitter(init, cfg, 3.0)
    fitter.train_until(5, views, progress=False)
    branch = copy.deepcopy(fitter)
    fitter.train_until(12, views, progress=False)
    assert branch.iteration == 5
    branch.train_until(12, views, progress=False)
    assert len(branch.model) == len(fitter.model)
    for a, b in zip(fitter.model.parameters(), branch.model.parameters()):
        assert torch.allclose(a, b, atol=1e-4)  # multi-threaded reductions may differ in the last bits


def test_densification_keeps_optimizer_and_model_in_sync():
    views, cfg, init = small_problem()
    fitter = GaussianFitter(init, cfg, 3.0)
    fitter.train_until(12, views, progress=False)
    for name, param in fitter.model.parameter_dict().items():
        assert fitter.optimizers[name].param_groups[0]["params"][0] is param


def test_photometric_loss_is_l1_plus_weighted_dssim():
    image = torch.rand(3, 16, 16, generator=torch.Generator().manual_seed(0))
    assert photometric_loss(image, image, 0.2).item() == pytest.approx(0.0, abs=1e-6)
    shifted = (image + 0.1).clamp(0, 1)
    l1 = (shifted - image).abs().mean().item()
    assert photometric_loss(shifted, image, 0.0).item() == pytest.approx(l1, rel=1e-6)
    assert photometric_loss(shifted, image, 0.2).item() > 0.8 * l1


@pytest.mark.parametrize("window", [11, 7])
def test_stacked_ssim_equals_kornia_in_value_and_gradient(window):
    """The fitter's SSIM blurs its five moments in one call; it must be kornia's SSIM, gradients included."""
    import kornia

    generator = torch.Generator().manual_seed(1)
    target = torch.rand(3, 48, 72, generator=generator)
    ours = torch.rand(3, 48, 72, generator=generator, requires_grad=True)
    theirs = ours.detach().clone().requires_grad_(True)
    mean_ssim(ours, target, window).backward()
    reference = kornia.metrics.ssim(theirs[None], target[None], window).mean()
    reference.backward()
    assert mean_ssim(ours, target, window).item() == pytest.approx(reference.item(), abs=1e-6)
    torch.testing.assert_close(ours.grad, theirs.grad, rtol=1e-4, atol=1e-9)


def test_fitter_input_errors_are_clear():
    views, cfg, init = small_problem()
    with pytest.raises(ValueError, match="scene_extent"):
        GaussianFitter(init, cfg, 0.0)
    with pytest.raises(ValueError, match="captured"):
        GaussianFitter(init, cfg, 1.0).train_until(3, [], progress=False)
    with pytest.raises(ValueError, match=r"View.image"):
        View(torch.zeros(1, 10, 10), views[0].camera)
