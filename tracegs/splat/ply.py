"""PLY export/import in the layout of the reference 3DGS implementation, which splat viewers read:
x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3 (float32; f_rest channel-major, opacity as
a logit, scales as logs, rotations as w x y z)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from tracegs.io import atomic_write
from tracegs.splat.gaussians import NUM_SH_REST, GaussianModel

DC_NAMES = [f"f_dc_{i}" for i in range(3)]
REST_NAMES = [f"f_rest_{i}" for i in range(3 * NUM_SH_REST)]
SCALE_NAMES = [f"scale_{i}" for i in range(3)]
ROT_NAMES = [f"rot_{i}" for i in range(4)]
PROPERTIES = ["x", "y", "z", "nx", "ny", "nz", *DC_NAMES, *REST_NAMES, "opacity", *SCALE_NAMES, *ROT_NAMES]


def save_ply(model: GaussianModel, path: str | os.PathLike) -> None:
    """Write `model` as a binary little-endian 3DGS PLY (atomically)."""
    n = len(model)
    with torch.no_grad():
        columns = torch.cat([
            model.means, torch.zeros(n, 3, device=model.means.device),
            model.sh_dc.transpose(1, 2).reshape(n, -1), model.sh_rest.transpose(1, 2).reshape(n, -1),
            model.opacity_logits[:, None], model.log_scales, model.quats,
        ], dim=1).float().cpu().numpy()
    vertices = np.empty(n, dtype=[(name, "f4") for name in PROPERTIES])
    for index, name in enumerate(PROPERTIES):
        vertices[name] = columns[:, index]
    with atomic_write(path) as tmp:
        PlyData([PlyElement.describe(vertices, "vertex")]).write(str(tmp))


def load_ply(path: str | os.PathLike) -> GaussianModel:
    """Read a 3DGS PLY (SH degree 0-3; missing higher-order coefficients are zero)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no PLY file at {path}")
    vertices = PlyData.read(str(path))["vertex"]
    names = {prop.name for prop in vertices.properties}
    required = ["x", "y", "z", *DC_NAMES, "opacity", *SCALE_NAMES, *ROT_NAMES]
    missing = [name for name in required if name not in names]
    if missing:
        raise ValueError(f"{path} is not a 3DGS PLY: missing vertex properties {missing}")

    def stack(keys: list[str]) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(vertices[key], dtype=np.float32) for key in keys], axis=1))

    n = len(vertices.data)
    rest_keys = sorted((name for name in names if name.startswith("f_rest_")), key=lambda k: int(k.split("_")[-1]))
    if len(rest_keys) % 3 or len(rest_keys) > 3 * NUM_SH_REST:
        raise ValueError(f"{path}: {len(rest_keys)} f_rest properties do not match an SH degree <= 3")
    per_channel = len(rest_keys) // 3
    sh_rest = torch.zeros(n, NUM_SH_REST, 3)
    if per_channel:
        sh_rest[:, :per_channel] = stack(rest_keys).reshape(n, 3, per_channel).transpose(1, 2)
    return GaussianModel(
        means=stack(["x", "y", "z"]), quats=stack(ROT_NAMES), log_scales=stack(SCALE_NAMES),
        opacity_logits=stack(["opacity"])[:, 0], sh_dc=stack(DC_NAMES)[:, None, :], sh_rest=sh_rest,
    )
