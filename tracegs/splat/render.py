"""`render`: one signature for every rasterizer backend (compiled CPU, pure PyTorch, dense, gsplat on CUDA)."""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from tracegs.errors import ConfigError
from tracegs.splat.cameras import Camera
from tracegs.splat.config import GaussianFitConfig, RenderBackend
from tracegs.splat.gaussians import MAX_SH_DEGREE, GaussianModel
from tracegs.splat.preprocess_compiled import preprocess_compiled
from tracegs.splat.projection import project_gaussians, radii_from_extents, visible_mask
from tracegs.splat.rasterize import rasterize_dense, rasterize_tiles
from tracegs.splat.rasterize_compiled import compiled_unavailable, rasterize_compiled
from tracegs.splat.sh import sh_to_rgb


@dataclass
class RenderOutput:
    """`image` [3,H,W], `alpha` [1,H,W], `depth` [1,H,W] (expected depth normalised by alpha, 0 where empty),
    `info`: what gsplat's densification strategies read (`means2d` [1,N,2] with retained grad, `radii` [1,N,2],
    `width`, `height`, `n_cameras`, `gaussian_ids`)."""

    image: Tensor
    alpha: Tensor
    depth: Tensor
    info: dict = field(default_factory=dict)


def gsplat_available() -> bool:
    return importlib.util.find_spec("gsplat") is not None and torch.cuda.is_available()


def require_available(backend: str, field: str) -> None:
    """Fail before any work when ``backend`` cannot run on this machine: gsplat needs CUDA and its package, the
    compiled backend (``auto`` on the CPU) a library this machine can build (:func:`require_compiled`)."""
    if backend == "gsplat" and not gsplat_available():
        raise ValueError(f"{field}='gsplat' needs CUDA and the gsplat package; use 'torch' (CPU) or 'auto' here")
    if backend == "compiled" or (backend == "auto" and not gsplat_available()):
        require_compiled(backend, field)


def require_compiled(backend: str, field: str) -> None:
    """Refuse ``backend`` (``auto`` or ``compiled`` at ``field``) where the compiled rasterizer cannot be built.

    ``auto`` does not fall back to the pure-PyTorch rasterizer: the two differ by ~3e-7 per render, which a 3DGS
    fit amplifies to tenths of a dB, and the run's folder is named by the configured value (tracegs.config.identity)
    -- a silent fallback would put other numbers under the same name. Recording the resolution in the identity
    instead would make a folder's name depend on the machine and on a C++ build at composition time, so a later
    stage on another machine would not find an earlier stage's product; asking for ``torch`` names its own folder
    with no such dependence."""
    problem = compiled_unavailable()
    if problem is not None:
        raise ConfigError(field, f"'{backend}' renders with the compiled CPU rasterizer, which cannot be built here "
                                 f"({problem}); install a C++ compiler (and ninja), or set {field}=torch for the "
                                 "pure-PyTorch rasterizer (slower, numbers slightly different: its products get "
                                 "their own folders)")


def resolve_backend(backend: str, device: torch.device, dtype: torch.dtype = torch.float32) -> str:
    """The backend `render` uses; "auto" keeps float64 models (gradient checks) on the exact torch backend, the
    compiled one computes in float32; it never falls back from the compiled one (:func:`require_compiled`)."""
    backend = RenderBackend.parse(backend, "render backend").value
    if backend == "auto":
        if device.type == "cuda":
            return "gsplat" if gsplat_available() else "torch"
        if dtype != torch.float32:
            return "torch"
        require_compiled("auto", "render backend")
        return "compiled"
    if backend == "gsplat" and (device.type != "cuda" or not gsplat_available()):
        raise ValueError("render backend 'gsplat' needs the gsplat package and the model on a CUDA device")
    if backend == "compiled" and device.type != "cpu":
        raise ValueError(f"render backend 'compiled' runs on the CPU, the model is on {device}")
    if backend == "compiled":
        require_compiled("compiled", "render backend")
    return backend


def fit_device(cfg: GaussianFitConfig) -> torch.device:
    """Where 3DGS fits and renders run: CUDA when the backend can use gsplat there, else the CPU."""
    return torch.device("cuda" if cfg.backend in ("auto", "gsplat") and gsplat_available() else "cpu")


@torch.no_grad()
def render_each(model: GaussianModel, cameras: Sequence[Camera], background: Sequence[float] | Tensor,
                sh_degree: int | None, backend: str = "auto") -> list[Tensor]:
    """Renders [3,H,W] in [0,1] of ``model`` at ``cameras``, each at its camera's size, on the model's device."""
    background = torch.as_tensor(background, dtype=torch.float32)
    return [render(model, camera, background, sh_degree, backend).image.clamp(0, 1) for camera in cameras]


def render_views(model: GaussianModel, cameras: Sequence[Camera], background: Sequence[float] | Tensor,
                 sh_degree: int | None, backend: str = "auto") -> Tensor:
    """Renders [F,3,H,W] in [0,1] of ``model`` at ``cameras`` of one size, on the model's device."""
    return torch.stack(render_each(model, cameras, background, sh_degree, backend))


def render_clip(model: GaussianModel, cameras: Sequence[Camera], fit: GaussianFitConfig, iteration: int) -> Tensor:
    """The frames [F,3,H,W] of one restorer clip R = Render(G, P), the single path by which prepare renders
    the training conditions (R_s, R_d) and deployment renders the clips it restores (supplement Eq.
    supp-round-rendering): the fit's background and backend, on the fit's device, at the SH degree the
    fit had reached at ``iteration``, so the restorer deploys on the inputs it was trained on."""
    model = model.to(fit_device(fit))
    return render_views(model, cameras, fit.background, fit.sh_degree_at(iteration), fit.backend)


def render(model: GaussianModel, camera: Camera, background: Tensor | None = None, sh_degree: int | None = None,
           backend: str = "auto") -> RenderOutput:
    """Render `model` from `camera` (main paper: R = Render(G, P)).

    backend: "compiled" (projection, SH and the tile rasterizer as compiled C++, CPU), "torch" (tile-culled pure
    PyTorch, any device), "dense" (every Gaussian at every pixel; slow reference), "gsplat" (CUDA), "auto" (gsplat
    for CUDA tensors when importable, compiled for float32 on the CPU, refused where it cannot be built).
    """
    degree = MAX_SH_DEGREE if sh_degree is None else sh_degree
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must lie in [0, {MAX_SH_DEGREE}], got {sh_degree}")
    means = model.means
    camera = camera.to(device=means.device, dtype=means.dtype)
    if background is None:
        background = means.new_zeros(3)
    background = background.to(means)
    backend = resolve_backend(backend, means.device, means.dtype)
    if backend == "gsplat":
        return _render_gsplat(model, camera, background, degree)
    if backend == "compiled":
        return _render_compiled(model, camera, background, degree)
    return _render_cpu(model, camera, background, degree, backend)


def _render_cpu(model: GaussianModel, camera: Camera, background: Tensor, degree: int, backend: str) -> RenderOutput:
    """Projection and SH in PyTorch autograd, then the `backend` rasterizer ("torch" or "dense")."""
    width, height = camera.width, camera.height
    opacities = model.opacities
    projected = project_gaussians(model.means, model.quats, model.log_scales, opacities, camera)
    means2d = projected.means2d[None]  # [1,N,2]: the tensor whose gradient densification accumulates
    if means2d.requires_grad:
        means2d.retain_grad()
    visible = visible_mask(projected, opacities, width, height)
    index = visible.nonzero().squeeze(1)
    index = index[torch.argsort(projected.depths.detach()[index], stable=True)]

    def gather(values: Tensor) -> Tensor:  # index_select: a faster gather than x[index], the same values
        return values.index_select(0, index)

    colours = sh_to_rgb(degree, gather(model.sh), gather(model.means) - camera.center)
    features = torch.cat([colours, gather(projected.depths)[:, None]], dim=-1)
    splat = (gather(means2d[0]), gather(projected.conics), gather(opacities), features)
    if backend == "dense":
        out, transmittance = rasterize_dense(*splat, width, height)
    else:
        out, transmittance = rasterize_tiles(*splat, gather(projected.extents), width, height)
    radii = radii_from_extents(projected.extents, visible)[None]
    return _composed_output(out, transmittance, background, means2d, radii, visible)


def _render_compiled(model: GaussianModel, camera: Camera, background: Tensor, degree: int) -> RenderOutput:
    """Projection, SH and compositing all compiled: two autograd nodes (and the opacity sigmoid) per render."""
    opacities = model.opacities
    pre = preprocess_compiled(model.means, model.quats, model.log_scales, opacities, model.sh_dc, model.sh_rest,
                              camera, degree)
    if pre.means2d.requires_grad:
        pre.means2d.retain_grad()
    out, transmittance = rasterize_compiled(pre.means2d, pre.conics, opacities, pre.features, pre.extents,
                                            camera.width, camera.height, order=pre.order)
    return _composed_output(out, transmittance, background, pre.means2d, pre.radii, pre.visible)


def _composed_output(out: Tensor, transmittance: Tensor, background: Tensor, means2d: Tensor, radii: Tensor,
                     visible: Tensor) -> RenderOutput:
    """The render from composited colour and depth `out` [H,W,4] and the final `transmittance` [H,W]."""
    height, width = transmittance.shape
    image = out[..., :3] + transmittance[..., None] * background
    alpha = 1.0 - transmittance
    depth = out[..., 3] / alpha.clamp_min(1e-10)
    info = {"means2d": means2d, "radii": radii, "width": width, "height": height, "n_cameras": 1,
            "gaussian_ids": None, "visible": visible}
    return RenderOutput(image.permute(2, 0, 1), alpha[None], depth[None], info)


def _render_gsplat(model: GaussianModel, camera: Camera, background: Tensor, degree: int) -> RenderOutput:
    from gsplat import rasterization

    colours, alphas, meta = rasterization(
        means=model.means, quats=model.quats, scales=model.scales, opacities=model.opacities, colors=model.sh,
        viewmats=camera.world_to_camera[None], Ks=camera.K[None], width=camera.width, height=camera.height,
        sh_degree=degree, backgrounds=background[None], render_mode="RGB+ED", packed=False,
    )
    meta["n_cameras"] = 1
    return RenderOutput(colours[0, ..., :3].permute(2, 0, 1), alphas[0].permute(2, 0, 1),
                        colours[0, ..., 3:].permute(2, 0, 1), meta)
