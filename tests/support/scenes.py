"""Shared tiny scenes for the splatting tests."""

from __future__ import annotations

import math

import torch

from tracegs.splat.cameras import Camera
from tracegs.splat.gaussians import GaussianModel

PARAMETER_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


def ring_cameras(count: int, radius: float = 3.5, width: int = 72, height: int = 48) -> list[Camera]:
    """Cameras on a wavy ring around the origin (z up), all looking at it."""
    cameras = []
    for k in range(count):
        theta = 2 * math.pi * k / count
        eye = torch.tensor([radius * math.cos(theta), radius * math.sin(theta), 0.6 * math.sin(3 * theta)])
        cameras.append(Camera.look_at(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]), fov_x_deg=50.0,
                                      width=width, height=height))
    return cameras


def random_scene(n: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> GaussianModel:
    """Anisotropic, rotated, view-dependent Gaussians inside the unit ball."""
    generator = torch.Generator().manual_seed(seed)
    model = GaussianModel.random(n, radius=1.0, generator=generator, initial_opacity=0.5)
    with torch.no_grad():
        model.quats.copy_(torch.randn(n, 4, generator=generator))
        model.log_scales.add_(0.4 * torch.randn(n, 3, generator=generator))
        model.opacity_logits.copy_(torch.randn(n, generator=generator))
        model.sh_rest.copy_(0.1 * torch.randn(n, 15, 3, generator=generator))
    return model.to(dtype)


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return (-10.0 * torch.log10((a - b).square().mean())).item()
