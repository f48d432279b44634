"""Rasterizer correctness: closed-form footprints, compositing, gradients, backend agreement."""

from __future__ import annotations

import math

import pytest
import torch
from support.scenes import PARAMETER_NAMES, random_scene, ring_cameras

from tracegs.splat.cameras import Camera
from tracegs.splat.gaussians import GaussianModel, rgb_to_sh_dc
from tracegs.splat.render import render


def single_gaussian(position, scales, quat, opacity: float, rgb, dtype=torch.float64) -> GaussianModel:
    return GaussianModel(
        means=torch.tensor([position], dtype=dtype), quats=torch.tensor([quat], dtype=dtype),
        log_scales=torch.tensor([scales], dtype=dtype).log(),
        opacity_logits=torch.tensor([math.log(opacity / (1 - opacity))], dtype=dtype),
        sh_dc=rgb_to_sh_dc(torch.tensor([[rgb]], dtype=dtype)), sh_rest=torch.zeros(1, 15, 3, dtype=dtype))


def fitted_footprint(alpha: torch.Tensor, opacity: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Recover the 2D mean and covariance from log(alpha / o) = -1/2 (p - m)^T S^-1 (p - m) by least squares."""
    ys, xs = torch.nonzero(alpha > 2.0 / 255.0, as_tuple=True)
    x, y = xs.double() + 0.5, ys.double() + 0.5
    target = torch.log(alpha[ys, xs].double() / opacity)
    design = torch.stack([x * x, x * y, y * y, x, y, torch.ones_like(x)], dim=1)
    qa, qb, qc, la, lb, _ = torch.linalg.lstsq(design, target[:, None]).solution[:, 0]
    precision = -2.0 * torch.stack([torch.stack([qa, qb / 2]), torch.stack([qb / 2, qc])])
    mean = torch.linalg.solve(precision, torch.stack([la, lb]))
    return mean, torch.linalg.inv(precision)


def test_single_gaussian_footprint_matches_ewa_projection():
    camera = Camera.look_at(torch.tensor([0.3, -4.0, 1.0]), torch.tensor([0.1, 0.0, 0.2]),
                            torch.tensor([0.0, 0.0, 1.0]), fov_x_deg=60.0, width=72, height=48).to(dtype=torch.float64)
    quat = torch.nn.functional.normalize(torch.tensor([0.9, 0.2, -0.3, 0.25]), dim=0).tolist()
    position, scales, opacity = [0.2, 0.1, 0.3], [0.12, 0.05, 0.08], 0.7
    model = single_gaussian(position, scales, quat, opacity, [0.2, 0.5, 0.8])
    alpha = render(model, camera, backend="torch").alpha[0]

    # Closed form: pinhole projection of the centre, J R Sigma R^T J^T + 0.3 I for the covariance.
    w, x, y, z = quat
    rot = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=torch.float64)
    sigma = rot @ torch.diag(torch.tensor(scales, dtype=torch.float64) ** 2) @ rot.T
    p = camera.rotation @ torch.tensor(position, dtype=torch.float64) + camera.translation
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    expected_mean = torch.stack([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy])
    jac = torch.tensor([[fx / p[2], 0, -fx * p[0] / p[2] ** 2], [0, fy / p[2], -fy * p[1] / p[2] ** 2]],
                       dtype=torch.float64)
    expected_cov = jac @ camera.rotation @ sigma @ camera.rotation.T @ jac.T + 0.3 * torch.eye(2, dtype=torch.float64)

    mean, cov = fitted_footprint(alpha, opacity)
    assert torch.allclose(mean, expected_mean, atol=1e-4)
    assert torch.allclose(cov, expected_cov, atol=1e-4)


def test_on_axis_isotropic_gaussian_is_centred_with_closed_form_size():
    camera = Camera.look_at(torch.tensor([0.0, 0.0, -5.0]), torch.zeros(3), torch.tensor([0.0, -1.0, 0.0]),
                            fov_x_deg=50.0, width=64, height=48).to(dtype=torch.float64)
    model = single_gaussian([0.0, 0.0, 0.0], [0.1, 0.1, 0.1], [1.0, 0.0, 0.0, 0.0], 0.5, [1.0, 1.0, 1.0])
    alpha = render(model, camera, backend="torch").alpha[0]
    mean, cov = fitted_footprint(alpha, 0.5)
    focal = camera.K[0, 0].item()
    # Principal point at the image centre = the corner shared by the four middle pixels (pixel centres at +0.5).
    assert torch.allclose(mean, torch.tensor([32.0, 24.0], dtype=torch.float64), atol=1e-4)
    expected = (focal * 0.1 / 5.0) ** 2 + 0.3
    assert torch.allclose(cov, expected * torch.eye(2, dtype=torch.float64), atol=1e-4)
    # The four middle pixels are equidistant from the centre.
    middle = alpha[23:25, 31:33]
    assert torch.allclose(middle, middle[0, 0].expand(2, 2), atol=1e-12)


def test_two_gaussians_composite_front_to_back():
    camera = Camera.look_at(torch.tensor([0.0, 0.0, -5.0]), torch.zeros(3), torch.tensor([0.0, -1.0, 0.0]),
                            fov_x_deg=50.0, width=32, height=24).to(dtype=torch.float64)
    front = dict(position=[0.0, 0.0, -1.0], scales=[0.3, 0.3, 0.3], opacity=0.6, rgb=[1.0, 0.0, 0.0])
    back = dict(position=[0.0, 0.0, 1.0], scales=[0.4, 0.4, 0.4], opacity=0.8, rgb=[0.0, 0.0, 1.0])
    # Stored back first: the renderer must sort by depth.
    parts = [single_gaussian(g["position"], g["scales"], [1.0, 0, 0, 0], g["opacity"], g["rgb"]) for g in (back, front)]
    model = GaussianModel(*(torch.cat([getattr(p, name) for p in parts]) for name in PARAMETER_NAMES))
    background = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = render(model, camera, background, backend="torch")

    focal = camera.K[0, 0].item()
    row, col = 13, 17
    pixel = torch.tensor([col + 0.5, row + 0.5], dtype=torch.float64)

    def alpha_of(g) -> float:
        depth = 5.0 + g["position"][2]
        centre = torch.tensor([focal * g["position"][0] / depth + 16.0, focal * g["position"][1] / depth + 12.0],
                              dtype=torch.float64)
        variance = (focal * g["scales"][0] / depth) ** 2 + 0.3
        return g["opacity"] * math.exp(-0.5 * float(((pixel - centre) ** 2).sum()) / variance)

    a1, a2 = alpha_of(front), alpha_of(back)
    assert 1 / 255 < a2 < 0.99 and 1 / 255 < a1 < 0.99
    c1, c2 = torch.tensor(front["rgb"], dtype=torch.float64), torch.tensor(back["rgb"], dtype=torch.float64)
    expected = a1 * c1 + (1 - a1) * a2 * c2 + (1 - a1) * (1 - a2) * background
    assert torch.allclose(out.image[:, row, col], expected, atol=1e-6)
    assert out.alpha[0, row, col].item() == pytest.approx(1 - (1 - a1) * (1 - a2), abs=1e-6)
    expected_depth = (a1 * 4.0 + (1 - a1) * a2 * 6.0) / (1 - (1 - a1) * (1 - a2))
    assert out.depth[0, row, col].item() == pytest.approx(expected_depth, abs=1e-6)


def test_gradcheck_float64_tiny_scene():
    camera = ring_cameras(1, width=12, height=8)[0].to(dtype=torch.float64)
    template = random_scene(3, seed=3, dtype=torch.float64)
    with torch.no_grad():
        template.log_scales.add_(1.0)
    inputs = tuple(getattr(template, name).detach().clone().requires_grad_() for name in PARAMETER_NAMES)
    background = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)

    def rendered(*tensors):
        model = template.clone()
        for name, tensor in zip(PARAMETER_NAMES, tensors):
            delattr(model, name)
            setattr(model, name, tensor)
        out = render(model, camera, background, backend="torch")
        return out.image, out.alpha

    assert render(template, camera, backend="torch").alpha.max() > 0.3  # the scene is actually visible
    assert torch.autograd.gradcheck(rendered, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


def test_tile_backend_matches_dense_reference():
    model = random_scene(400, seed=1)
    camera = ring_cameras(3)[1]
    background = torch.tensor([0.2, 0.3, 0.4])
    tiled = render(model, camera, background, backend="torch")
    dense = render(model, camera, background, backend="dense")
    assert (tiled.image - dense.image).abs().max() < 1e-4
    assert (tiled.alpha - dense.alpha).abs().max() < 1e-4
    grads_tiled = torch.autograd.grad(tiled.image.square().sum(), list(model.parameters()))
    grads_dense = torch.autograd.grad(dense.image.square().sum(), list(model.parameters()))
    for g_t, g_d in zip(grads_tiled, grads_dense):
        assert torch.allclose(g_t, g_d, atol=1e-4 * g_d.abs().max().item() + 1e-8)


def test_render_info_feeds_densification():
    model = random_scene(50, seed=2)
    out = render(model, ring_cameras(1)[0], backend="torch")
    out.image.sum().backward()
    info = out.info
    assert info["means2d"].shape == (1, 50, 2) and info["means2d"].grad is not None
    visible = info["radii"][0].gt(0).all(dim=-1)
    assert visible.any() and not info["means2d"].grad[0][~visible].any()
    assert (info["width"], info["height"], info["n_cameras"]) == (72, 48, 1)


def test_gaussians_behind_the_camera_are_ignored():
    camera = ring_cameras(1)[0]
    behind = camera.center + 2.0 * (camera.center / camera.center.norm())
    model = GaussianModel.from_points(behind[None], torch.ones(1, 3))
    out = render(model, camera, backend="torch")
    assert out.alpha.abs().max() == 0
    out.image.sum().backward()
    assert torch.isfinite(model.means.grad).all()


def test_unknown_backend_and_cpu_gsplat_are_rejected():
    model = random_scene(5)
    with pytest.raises(ValueError, match="backend"):
        render(model, ring_cameras(1)[0], backend="vulkan")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="gsplat"):
            render(model, ring_cameras(1)[0], backend="gsplat")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gsplat_backend_matches_torch_backend():
    model = random_scene(300, seed=4).cuda()
    camera = ring_cameras(2)[1].to("cuda")
    background = torch.tensor([0.1, 0.2, 0.3], device="cuda")
    ours = render(model, camera, background, backend="torch")
    theirs = render(model, camera, background, backend="gsplat")
    assert (ours.image - theirs.image).abs().max() < 2e-2
    assert (ours.image - theirs.image).abs().mean() < 1e-3
    grads_ours = torch.autograd.grad(ours.image.sum(), [model.means, model.sh_dc])
    grads_theirs = torch.autograd.grad(theirs.image.sum(), [model.means, model.sh_dc])
    for ours_g, theirs_g in zip(grads_ours, grads_theirs):
        cosine = torch.nn.functional.cosine_similarity(ours_g.flatten(), theirs_g.flatten(), dim=0)
        assert cosine > 0.95
    assert render(model, camera, background).info.get("means2d") is not None  # "auto" picks gsplat on CUDA


def test_occluded_pairs_are_dropped_without_changing_the_result(monkeypatch):
    from tracegs.splat import rasterize

    model = random_scene(400, seed=6)
    with torch.no_grad():
        model.opacity_logits.add_(5.0)  # nearly opaque: deep pixels saturate, later splats are hidden
        model.log_scales.add_(0.5)
    camera = ring_cameras(3)[2]
    dropped = []
    forward = rasterize._TileComposite.forward

    def spying_forward(ctx, *args):
        result = forward(ctx, *args)
        dropped.append(args[0].shape[1] - (args[0].shape[1] if ctx.kept is None else len(ctx.kept)))
        return result

    monkeypatch.setattr(rasterize._TileComposite, "forward", staticmethod(spying_forward))
    monkeypatch.setattr(rasterize, "COMPACT_BELOW", 1.01)  # compact whenever anything is hidden
    tiled = render(model, camera, backend="torch")
    dense = render(model, camera, backend="dense")
    assert dropped[0] > 0
    assert (tiled.image - dense.image).abs().max() < 1e-4
    grads_tiled = torch.autograd.grad(tiled.image.sum(), [model.means, model.opacity_logits, model.sh_dc])
    grads_dense = torch.autograd.grad(dense.image.sum(), [model.means, model.opacity_logits, model.sh_dc])
    for g_t, g_d in zip(grads_tiled, grads_dense):
        assert torch.allclose(g_t, g_d, atol=1e-3 * g_d.abs().max().item())
