"""The 3D Gaussian scene model (3DGS parameterisation: log-scales, wxyz quaternions, opacity logits, SH)."""

from __future__ import annotations

import copy
import math

import torch
from torch import Tensor, nn

SH_C0 = 0.28209479177387814  # Y_0^0; maps an RGB colour to the degree-0 SH coefficient (colour = C0 * dc + 0.5)
MAX_SH_DEGREE = 3
NUM_SH_REST = (MAX_SH_DEGREE + 1) ** 2 - 1

# Parameter names of this model and the names gsplat's densification strategies expect for them.
GSPLAT_NAMES = {
    "means": "means",
    "quats": "quats",
    "log_scales": "scales",
    "opacity_logits": "opacities",
    "sh_dc": "sh0",
    "sh_rest": "shN",
}


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    return (rgb - 0.5) / SH_C0


def nearest_neighbour_distance(xyz: Tensor, k: int = 3, chunk: int = 4096) -> Tensor:
    """Root of the mean squared distance to the `k` nearest other points (3DGS scale initialisation)."""
    k = min(k, xyz.shape[0] - 1)
    if k < 1:
        return torch.ones(xyz.shape[0], dtype=xyz.dtype, device=xyz.device)
    out = []
    for start in range(0, xyz.shape[0], chunk):  # chunked so paper-scale point clouds fit in memory
        dist2 = torch.cdist(xyz[start:start + chunk], xyz).square()
        nearest = dist2.topk(k + 1, dim=1, largest=False).values[:, 1:]  # drop the point itself
        out.append(nearest.mean(dim=1).sqrt())
    return torch.cat(out)


class GaussianModel(nn.Module):
    """N anisotropic 3D Gaussians with view-dependent colour (spherical harmonics up to degree 3).

    Parameters: `means` [N,3], `quats` [N,4] (w,x,y,z, unnormalised), `log_scales` [N,3],
    `opacity_logits` [N], `sh_dc` [N,1,3], `sh_rest` [N,15,3].
    """

    def __init__(self, means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, sh_dc: Tensor,
                 sh_rest: Tensor):
        super().__init__()
        n = means.shape[0]
        expected = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,),
                    "sh_dc": (n, 1, 3), "sh_rest": (n, NUM_SH_REST, 3)}
        given = {"means": means, "quats": quats, "log_scales": log_scales, "opacity_logits": opacity_logits,
                 "sh_dc": sh_dc, "sh_rest": sh_rest}
        for name, tensor in given.items():
            if tuple(tensor.shape) != expected[name]:
                raise ValueError(f"GaussianModel.{name} must have shape {expected[name]}, got {tuple(tensor.shape)}")
            setattr(self, name, nn.Parameter(tensor.detach().clone()))

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def scales(self) -> Tensor:
        return self.log_scales.exp()

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def sh(self) -> Tensor:
        """All SH coefficients [N,16,3]."""
        return torch.cat([self.sh_dc, self.sh_rest], dim=1)

    def clone(self) -> GaussianModel:
        return copy.deepcopy(self)

    def parameter_dict(self) -> dict[str, nn.Parameter]:
        """The parameters keyed by gsplat's names (what gsplat strategies operate on)."""
        return {gsplat_name: getattr(self, name) for name, gsplat_name in GSPLAT_NAMES.items()}

    def load_parameter_dict(self, params: dict[str, nn.Parameter]) -> None:
        """Adopt parameters a gsplat strategy replaced (densification changes their number)."""
        for name, gsplat_name in GSPLAT_NAMES.items():
            setattr(self, name, params[gsplat_name])

    @classmethod
    def from_points(cls, xyz: Tensor, rgb: Tensor, initial_opacity: float = 0.1,
                    scale_multiplier: float = 1.0) -> GaussianModel:
        """Isotropic Gaussians at SfM points, sized by their nearest-neighbour distance (as 3DGS does)."""
        if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape:
            raise ValueError(f"from_points needs xyz and rgb of shape (N, 3), got {tuple(xyz.shape)}, "
                             f"{tuple(rgb.shape)}")
        if not 0.0 < initial_opacity < 1.0:
            raise ValueError(f"initial_opacity must lie in (0, 1), got {initial_opacity}")
        xyz = xyz.float()
        n = xyz.shape[0]
        distance = nearest_neighbour_distance(xyz).clamp_min(1e-7) * scale_multiplier
        quats = torch.zeros(n, 4, device=xyz.device)
        quats[:, 0] = 1.0
        return cls(
            means=xyz,
            quats=quats,
            log_scales=distance.log()[:, None].repeat(1, 3),
            opacity_logits=torch.full((n,), math.log(initial_opacity / (1.0 - initial_opacity)), device=xyz.device),
            sh_dc=rgb_to_sh_dc(rgb.float().clamp(0.0, 1.0))[:, None, :],
            sh_rest=torch.zeros(n, NUM_SH_REST, 3, device=xyz.device),
        )

    @classmethod
    def random(cls, n: int, center: Tensor | tuple[float, float, float] = (0.0, 0.0, 0.0), radius: float = 1.0,
               generator: torch.Generator | None = None, initial_opacity: float = 0.1) -> GaussianModel:
        """`n` Gaussians uniformly distributed in a ball, with random colours."""
        if n < 1:
            raise ValueError(f"GaussianModel.random needs n >= 1, got {n}")
        direction = torch.randn(n, 3, generator=generator)
        direction = direction / direction.norm(dim=1, keepdim=True).clamp_min(1e-12)
        distance = radius * torch.rand(n, 1, generator=generator).pow(1.0 / 3.0)
        xyz = torch.as_tensor(center, dtype=torch.float32) + direction * distance
        rgb = torch.rand(n, 3, generator=generator)
        return cls.from_points(xyz, rgb, initial_opacity=initial_opacity)
