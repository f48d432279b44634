"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (Zwicker et al. 2001, as in 3DGS)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from tracegs.splat.cameras import Camera

LOW_PASS_VARIANCE = 0.3  # 3DGS adds 0.3 px^2 to every 2D covariance so each splat covers at least ~1 pixel
NEAR_PLANE = 0.01
ALPHA_MIN = 1.0 / 255.0  # 3DGS skips contributions below this alpha
FOV_CLAMP = 1.3  # 3DGS clamps the Jacobian's x/z, y/z to 1.3x the half field of view for off-screen stability


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [N,3,3] from (w,x,y,z) quaternions [N,4] (normalised here)."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def covariance_factor(quats: Tensor, log_scales: Tensor) -> Tensor:
    """R S [N,3,3], the factor of the world-space covariance Sigma = (R S)(R S)^T."""
    return quat_to_rotmat(quats) * log_scales.exp()[:, None, :]


@dataclass
class ProjectedGaussians:
    """Screen-space Gaussians of one camera; all fields have N rows (culling happens later)."""

    means2d: Tensor  # [N,2] pixels
    conics: Tensor  # [N,3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]
    depths: Tensor  # [N] camera-space z
    extents: Tensor  # [N,2] half-widths (px) of the box outside which alpha < 1/255 (no gradient)
    in_front: Tensor  # [N] bool, beyond the near plane


def project_gaussians(means: Tensor, quats: Tensor, log_scales: Tensor, opacities: Tensor,
                      camera: Camera) -> ProjectedGaussians:
    """Project to 2D with the local affine (EWA) approximation J W Sigma W^T J^T + 0.3 I."""
    rotation, translation = camera.rotation, camera.translation
    p_cam = means @ rotation.T + translation
    in_front = p_cam[:, 2] > NEAR_PLANE
    # Gaussians behind the camera get a harmless depth so no inf/NaN reaches the backward pass.
    tz = torch.where(in_front, p_cam[:, 2], torch.ones_like(p_cam[:, 2]))
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    u, v = p_cam[:, 0] / tz, p_cam[:, 1] / tz
    means2d = torch.stack([fx * u + cx, fy * v + cy], dim=-1)

    lim_x = FOV_CLAMP * 0.5 * camera.width / fx
    lim_y = FOV_CLAMP * 0.5 * camera.height / fy
    u_c, v_c = u.clamp(-lim_x, lim_x), v.clamp(-lim_y, lim_y)
    zeros = torch.zeros_like(tz)
    jacobian = torch.stack([fx / tz, zeros, -fx * u_c / tz, zeros, fy / tz, -fy * v_c / tz], dim=-1).reshape(-1, 2, 3)
    jw = jacobian @ rotation
    # J W Sigma W^T J^T = (J W R S)(J W R S)^T: two small batched products instead of three.
    jwrs = jw @ covariance_factor(quats, log_scales)
    cov2d = jwrs @ jwrs.transpose(1, 2)
    cxx = cov2d[:, 0, 0] + LOW_PASS_VARIANCE
    cxy = cov2d[:, 0, 1]
    cyy = cov2d[:, 1, 1] + LOW_PASS_VARIANCE
    det = cxx * cyy - cxy * cxy
    conics = torch.stack([cyy / det, -cxy / det, cxx / det], dim=-1)

    with torch.no_grad():
        # alpha = o exp(-d^T C^-1 d / 2) >= 1/255  <=>  d^T C^-1 d <= 2 ln(255 o): that ellipse's bounding box
        # is exact, so culling to it never changes the image (the dense reference agrees to rounding).
        reach2 = (2.0 * torch.log(opacities.detach() / ALPHA_MIN)).clamp_min(0.0)
        extents = torch.stack([cxx, cyy], dim=-1).clamp_min(0.0).sqrt() * reach2.sqrt()[:, None]
    return ProjectedGaussians(means2d, conics, p_cam[:, 2], extents, in_front)


def visible_mask(projected: ProjectedGaussians, opacities: Tensor, width: int, height: int) -> Tensor:
    """Gaussians in front of the camera, opaque enough to ever pass 1/255, with a box touching the image."""
    m, e = projected.means2d.detach(), projected.extents
    return (projected.in_front & (opacities.detach() >= ALPHA_MIN)
            & (m[:, 0] + e[:, 0] > 0) & (m[:, 0] - e[:, 0] < width)
            & (m[:, 1] + e[:, 1] > 0) & (m[:, 1] - e[:, 1] < height)
            & torch.isfinite(m).all(dim=-1))


def radii_from_extents(extents: Tensor, visible: Tensor) -> Tensor:
    """Integer screen radii [N,2] (0 = not rendered), the form gsplat's strategies read."""
    return torch.where(visible[:, None], extents.ceil().clamp_min(1.0), torch.zeros_like(extents)).to(torch.int32)

