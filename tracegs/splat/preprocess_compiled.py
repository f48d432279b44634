"""Per-Gaussian preprocessing of the compiled backend in C++: EWA projection and SH colour, forward and backward.

What `projection.project_gaussians`, `projection.visible_mask`, `projection.radii_from_extents` and
`sh.sh_to_rgb` compute for the torch backend, as one loop over the Gaussians with the chain rule written out by
hand (`preprocess_compiled.cpp`), the way gsplat fuses projection and spherical harmonics on CUDA. In PyTorch
these few hundred flops per Gaussian are hundreds of small tensor operations and autograd nodes whose fixed cost
was about that of the compiled compositing itself (half of a render); compiled, they cost several times less.
The PyTorch functions stay the readable reference; the tests compare both, images and gradients. Built into the
same library as the compiled rasterizer (`rasterize_compiled.py`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from tracegs.splat.cameras import Camera
from tracegs.splat.rasterize_compiled import library, pointer


@dataclass
class PreprocessedGaussians:
    """One camera's screen-space Gaussians; every field has N rows except `order`."""

    means2d: Tensor  # [1,N,2] pixels: in the autograd graph, densification reads its retained gradient
    conics: Tensor  # [N,3] (a, b, c) of the inverse 2D covariance
    features: Tensor  # [N,4] colour (0 where not visible) and camera-space depth
    extents: Tensor  # [N,2] half-widths of the 1/255-alpha box (no gradient)
    radii: Tensor  # [1,N,2] int32, 0 where not visible
    visible: Tensor  # [N] bool, as `projection.visible_mask`
    order: Tensor  # [M] int64: the visible Gaussians front to back (a stable sort by depth)


class _CompiledPreprocess(torch.autograd.Function):
    """Gradients flow from means2d, conics and features to means, quats, log_scales, sh_dc and sh_rest."""

    @staticmethod
    def forward(ctx, means: Tensor, quats: Tensor, log_scales: Tensor, opacities: Tensor, sh_dc: Tensor,
                sh_rest: Tensor, world_to_camera: Tensor, K: Tensor, width: int, height: int, degree: int):
        inputs = [x.detach().to(torch.float32).contiguous() for x in (means, quats, log_scales, opacities, sh_dc,
                                                                       sh_rest)]
        camera = [x.detach().to(torch.float32).contiguous() for x in (world_to_camera, K)]
        n = means.shape[0]
        means2d, conics = torch.empty(1, n, 2), torch.empty(n, 3)
        features, extents = torch.empty(n, 4), torch.empty(n, 2)
        radii = torch.empty(1, n, 2, dtype=torch.int32)
        visible = torch.empty(n, dtype=torch.bool)
        order = torch.empty(n, dtype=torch.int64)
        count = library().preprocess_forward(n, degree, width, height, *map(pointer, camera + inputs),
                                             *map(pointer, (means2d, conics, features, extents, radii, visible, order)))
        order = order[:count]
        ctx.mark_non_differentiable(extents, radii, visible, order)
        ctx.setup = (n, degree, width, height)
        ctx.dtypes = [x.dtype for x in (means, quats, log_scales, sh_dc, sh_rest)]
        ctx.save_for_backward(*camera, *inputs)
        return means2d, conics, features, extents, radii, visible, order

    @staticmethod
    def backward(ctx, grad_means2d: Tensor | None, grad_conics: Tensor | None, grad_features: Tensor | None, *_):
        world_to_camera, K, means, quats, log_scales, _opacities, sh_dc, sh_rest = ctx.saved_tensors
        n, degree, width, height = ctx.setup
        upstream = [torch.zeros(shape) if grad is None else grad.to(torch.float32).contiguous()
                    for grad, shape in ((grad_means2d, (1, n, 2)), (grad_conics, (n, 3)), (grad_features, (n, 4)))]
        grads = [torch.empty_like(x) for x in (means, quats, log_scales, sh_dc, sh_rest)]
        library().preprocess_backward(n, degree, width, height,
                                      *map(pointer, (world_to_camera, K, means, quats, log_scales, sh_dc, sh_rest)),
                                      *map(pointer, upstream), *map(pointer, grads))
        grad_means, grad_quats, grad_log_scales, grad_sh_dc, grad_sh_rest = (
            grad.to(dtype) for grad, dtype in zip(grads, ctx.dtypes))
        return grad_means, grad_quats, grad_log_scales, None, grad_sh_dc, grad_sh_rest, None, None, None, None, None


def preprocess_compiled(means: Tensor, quats: Tensor, log_scales: Tensor, opacities: Tensor, sh_dc: Tensor,
                        sh_rest: Tensor, camera: Camera, degree: int) -> PreprocessedGaussians:
    """Project CPU Gaussians for `camera` and colour them at SH `degree` (`opacities` only cull), computing in
    float32 (gradients come back in the parameters' dtype)."""
    outputs = _CompiledPreprocess.apply(means, quats, log_scales, opacities.detach(), sh_dc, sh_rest,
                                        camera.world_to_camera, camera.K, camera.width, camera.height, degree)
    return PreprocessedGaussians(*outputs)
