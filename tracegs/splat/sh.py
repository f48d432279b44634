"""Real spherical harmonics up to degree 3 in the 3DGS basis (colour = SH(dir) + 0.5).

Written by hand because gsplat's public `spherical_harmonics` needs CUDA and the embedded scale runs on CPU.
"""

from __future__ import annotations

import torch
from torch import Tensor

from tracegs.splat.gaussians import MAX_SH_DEGREE, SH_C0

SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def sh_basis(degree: int, directions: Tensor) -> Tensor:
    """Basis values [..., (degree+1)^2] at unit `directions` [..., 3]."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must lie in [0, {MAX_SH_DEGREE}], got {degree}")
    x, y, z = directions.unbind(-1)
    terms = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        terms += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        terms += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * x * z,
                  SH_C2[4] * (xx - yy)]
    if degree >= 3:
        terms += [SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4.0 * zz - xx - yy),
                  SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), SH_C3[4] * x * (4.0 * zz - xx - yy),
                  SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy)]
    return torch.stack(terms, dim=-1)


def sh_to_rgb(degree: int, coefficients: Tensor, directions: Tensor) -> Tensor:
    """View-dependent colour [N,3] from SH `coefficients` [N,>=(degree+1)^2,3] seen along `directions` [N,3]."""
    basis = sh_basis(degree, torch.nn.functional.normalize(directions, dim=-1))
    used = coefficients[:, : basis.shape[-1], :]
    return ((basis[:, :, None] * used).sum(dim=1) + 0.5).clamp_min(0.0)
