"""The compiled backend (projection, SH, compositing) against the pure-PyTorch reference and the dense oracle:
images, gradients at every SH degree, what densification reads, hard scenes (behind the camera, off screen,
degenerate, crowded tiles) and a whole fit."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from support.scenes import PARAMETER_NAMES, psnr, random_scene, ring_cameras

from tracegs.errors import ConfigError
from tracegs.splat.config import DensificationConfig, GaussianFitConfig
from tracegs.splat.fit import GaussianFitter, View, camera_extent
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.rasterize_compiled import compiled_unavailable, library, rasterize_compiled
from tracegs.splat.render import render, require_available, resolve_backend

pytestmark = pytest.mark.skipif(compiled_unavailable() is not None, reason="no C++ compiler: the compiled backend is off")


def hard_scene(seed: int) -> GaussianModel:
    """Random Gaussians plus the cases a rasterizer gets wrong: some behind the camera, some off screen, some
    with a degenerate (near-zero or needle) covariance, and a crowd of faint ones on one spot."""
    generator = torch.Generator().manual_seed(seed)
    camera = ring_cameras(3)[1]
    parts = [random_scene(300, seed=seed)]
    behind = random_scene(20, seed=seed + 1)
    off_screen = random_scene(20, seed=seed + 2)
    degenerate = random_scene(30, seed=seed + 3)
    crowd = random_scene(1500, seed=seed + 4)
    with torch.no_grad():
        behind.means.copy_(camera.center + 1.5 * camera.center / camera.center.norm()
                           + 0.3 * torch.randn(20, 3, generator=generator))
        right = torch.linalg.cross(-camera.center, torch.tensor([0.0, 0.0, 1.0]))
        off_screen.means.add_(6.0 * right / right.norm())
        degenerate.log_scales[:10].fill_(-20.0)  # a point: only the 0.3 px^2 low-pass filter is left
        degenerate.log_scales[10:20, :2].fill_(-20.0)  # needles
        degenerate.log_scales[20:, 0].fill_(-20.0)  # flat disks, some seen edge-on
        # 1500 faint splats on one spot: one tile holds far more splats than a fixed per-tile buffer of
        # 256 or 1024, and they stay visible (transmittance after 1500 of them is ~0.5e-3, above the cut-off).
        crowd.means.copy_(0.01 * torch.randn(1500, 3, generator=generator))
        crowd.log_scales.fill_(-3.5)
        crowd.opacity_logits.fill_(-5.5)
    parts += [behind, off_screen, degenerate, crowd]
    return GaussianModel(*(torch.cat([getattr(part, name) for part in parts]) for name in PARAMETER_NAMES))


def rendered_with_grads(model: GaussianModel, backend: str, sh_degree: int | None = None):
    camera = ring_cameras(3)[1]
    background = torch.tensor([0.2, 0.3, 0.4])
    out = render(model, camera, background, sh_degree, backend=backend)
    loss = out.image.square().sum() + 0.1 * out.depth.sum() + out.alpha.sum()
    parameters = [getattr(model, name) for name in PARAMETER_NAMES]
    grads = torch.autograd.grad(loss, parameters + [out.info["means2d"]])
    return out, grads


def assert_grads_close(ours, reference, relative: float):
    for name, g_ours, g_ref in zip((*PARAMETER_NAMES, "means2d"), ours, reference):
        scale = g_ref.abs().max().item()
        if name == "sh_rest" and scale == 0:  # SH degree 0: the higher coefficients are unused
            assert not g_ours.any(), name
            continue
        assert scale > 0, name
        assert (g_ours - g_ref).abs().max().item() <= relative * scale, name


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_matches_reference_backends_on_hard_scenes(seed, sh_degree):
    """Images and the gradients of every parameter and of the retained screen-space means agree with the
    pure-PyTorch autograd reference (projection, SH and compositing), at every SH degree."""
    model = hard_scene(seed)
    compiled, grads_compiled = rendered_with_grads(model, "compiled", sh_degree)
    reference, grads_reference = rendered_with_grads(model, "torch", sh_degree)
    crowd_pixel = compiled.info["means2d"][0, -1].round().long()
    assert compiled.alpha[0, crowd_pixel[1], crowd_pixel[0]] > 0.9  # the crowd is really on screen
    for field in ("image", "alpha", "depth"):
        difference = (getattr(compiled, field) - getattr(reference, field))
        if field == "depth":  # depth = sum w z / alpha: compare where the pixel is not empty
            difference = difference[reference.alpha > 1e-3]
        assert difference.abs().max() < 1e-4, field
    assert_grads_close(grads_compiled, grads_reference, 1e-3)
    used = (sh_degree + 1) ** 2 - 1
    assert not grads_compiled[PARAMETER_NAMES.index("sh_rest")][:, used:].any()  # coefficients above the degree
    assert torch.equal(compiled.info["radii"], reference.info["radii"])
    assert torch.equal(compiled.info["visible"], reference.info["visible"])
    assert not grads_compiled[-1][0][~compiled.info["visible"]].any()  # culled splats get no screen gradient
    assert all(torch.isfinite(g).all() for g in grads_compiled)


def test_view_dependent_colour_moves_the_means_as_in_the_reference():
    """Strong view-dependent colour: the gradient reaching the means through the viewing direction of the SH
    (about half of it here) matches the reference."""
    model = random_scene(400, seed=3)
    with torch.no_grad():
        model.sh_rest.mul_(5.0)
    compiled, grads_compiled = rendered_with_grads(model, "compiled")
    reference, grads_reference = rendered_with_grads(model, "torch")
    assert (compiled.image - reference.image).abs().max() < 1e-4
    assert_grads_close(grads_compiled, grads_reference, 1e-3)


def test_compiled_matches_dense_oracle():
    model = random_scene(400, seed=5)
    compiled, grads_compiled = rendered_with_grads(model, "compiled")
    dense, grads_dense = rendered_with_grads(model, "dense")
    assert (compiled.image - dense.image).abs().max() < 1e-4
    assert (compiled.alpha - dense.alpha).abs().max() < 1e-4
    assert_grads_close(grads_compiled, grads_dense, 1e-3)


def test_compiled_handles_empty_screens_and_other_tile_sizes():
    model = random_scene(5, seed=3)
    with torch.no_grad():
        model.means.add_(100.0)  # nothing on screen
    out = render(model, ring_cameras(1)[0], backend="compiled")
    assert out.alpha.abs().max() == 0
    out.image.sum().backward()
    assert torch.isfinite(model.means.grad).all()

    from tracegs.splat.rasterize import rasterize_tiles

    generator = torch.Generator().manual_seed(0)
    means2d = torch.rand(50, 2, generator=generator) * torch.tensor([40.0, 30.0])
    conics = torch.tensor([0.2, 0.05, 0.3]).repeat(50, 1)
    opacities = torch.rand(50, generator=generator)
    features = torch.rand(50, 4, generator=generator)
    extents = torch.full((50, 2), 8.0)
    for tile_size in (8, 16):
        ours = rasterize_compiled(means2d, conics, opacities, features, extents, 37, 29, tile_size)
        reference = rasterize_tiles(means2d, conics, opacities, features, extents, 37, 29, tile_size)
        for a, b in zip(ours, reference):
            assert (a - b).abs().max() < 1e-5
    with pytest.raises(ValueError, match="tile sizes"):
        rasterize_compiled(means2d, conics, opacities, features, extents, 37, 29, 5)


def test_auto_backend_is_compiled_on_cpu_float32_and_exact_for_float64():
    cpu = torch.device("cpu")
    assert resolve_backend("auto", cpu, torch.float32) == "compiled"
    assert resolve_backend("auto", cpu, torch.float64) == "torch"


def test_explicit_compiled_backend_computes_float64_models_in_float32():
    model = random_scene(300, seed=6, dtype=torch.float64)
    compiled, grads_compiled = rendered_with_grads(model, "compiled")
    reference, grads_reference = rendered_with_grads(model, "torch")
    assert (compiled.image - reference.image).abs().max() < 1e-4
    assert all(g.dtype == torch.float64 for g in grads_compiled[:-1])  # the parameters' dtype
    assert_grads_close(grads_compiled, grads_reference, 1e-3)


def test_fit_on_compiled_backend_matches_reference_backend_psnr():
    """A 3DGS fit with densification reaches the same training-view PSNR on both backends (within 0.05 dB)."""
    truth = random_scene(150, seed=11)
    cameras = ring_cameras(8)
    with torch.no_grad():
        views = [View(render(truth, camera, backend="torch").image.clamp(0, 1), camera) for camera in cameras]
    scores = {}
    for backend in ("compiled", "torch"):
        cfg = GaussianFitConfig(iterations=150, snapshot_iters=[150], backend=backend, sh_degree_interval=50,
                                densification=DensificationConfig(refine_start_iter=20, refine_every=20,
                                                                  refine_stop_iter=120, reset_every=1000))
        fitter = GaussianFitter(random_scene(100, seed=12), cfg, camera_extent(cameras))
        fitter.train_until(150, views, progress=False)
        with torch.no_grad():
            rendered = [render(fitter.model, view.camera, backend="torch").image for view in views]
        scores[backend] = sum(psnr(image, view.image) for image, view in zip(rendered, views)) / len(views)
    assert scores["torch"] > 20.0  # the fit did learn the scene
    assert abs(scores["compiled"] - scores["torch"]) <= 0.05, scores


def test_auto_refuses_to_fall_back_to_torch_when_the_build_fails(tmp_path, monkeypatch):
    """The two backends' numbers differ: where the library cannot be built, ``auto`` is refused naming the build's
    own complaint and the fix, never silently rendered by the pure-PyTorch rasterizer; ``torch`` asked for still
    renders."""
    from tracegs.splat import rasterize_compiled

    broken = tmp_path / "rasterize_compiled.cpp"
    broken.write_text("this is not C++\n")
    monkeypatch.setattr(rasterize_compiled, "SOURCES", (broken,))
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "extensions"))
    rasterize_compiled.library.cache_clear()
    rasterize_compiled.compiled_unavailable.cache_clear()
    try:
        with pytest.raises(ConfigError) as refused:
            require_available("auto", "data.prepare.fit.backend")
        message = str(refused.value)
        assert "\n" not in message and message.startswith("config field 'data.prepare.fit.backend': 'auto' ")
        assert "cannot be built here (RuntimeError: " in message and "error" in message.split("(RuntimeError: ")[1]
        assert "set data.prepare.fit.backend=torch" in message
        with pytest.raises(ConfigError, match="cannot be built here"):
            render(random_scene(20, seed=1), ring_cameras(1)[0])
        assert render(random_scene(20, seed=1), ring_cameras(1)[0], backend="torch").image.shape == (3, 48, 72)
    finally:
        rasterize_compiled.library.cache_clear()
        rasterize_compiled.compiled_unavailable.cache_clear()


def test_a_build_lock_left_by_a_killed_builder_does_not_stop_the_next_process(tmp_path):
    """torch's build lock is a file: a builder killed mid-build left it, and every later command waited on it
    forever. The next process now takes the build over."""
    built = Path(library()._name).parent
    extensions = tmp_path / "extensions"
    shutil.copytree(built, extensions / built.name)
    (extensions / built.name / "lock").touch()  # what a killed builder leaves
    run = subprocess.run([sys.executable, "-c", "from tracegs.splat.rasterize_compiled import library; library()"],
                         env={**os.environ, "TORCH_EXTENSIONS_DIR": str(extensions)}, timeout=120,
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]
    assert not (extensions / built.name / "lock").exists()
