"""Pinhole cameras in the OpenCV / COLMAP convention (x right, y down, z forward; pixel centres at +0.5)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


def intrinsics_from_fov(fov_x_deg: float, width: int, height: int) -> Tensor:
    """Square-pixel intrinsics with the principal point at the image centre."""
    if not 0.0 < fov_x_deg < 180.0:
        raise ValueError(f"fov_x_deg must lie in (0, 180), got {fov_x_deg}")
    focal = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2.0)
    return torch.tensor([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def look_at_rotation(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """World-to-camera rotation whose z axis points from `eye` to `target` and whose -y axis leans to `up`."""
    forward = target - eye
    if forward.norm() < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up.to(forward))
    if right.norm() < 1e-9:
        raise ValueError("look_at: up vector is parallel to the viewing direction")
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    return torch.stack([right, down, forward], dim=0)


@dataclass
class Camera:
    """A pinhole camera: intrinsics `K` [3,3], extrinsics `world_to_camera` [4,4], image size in pixels."""

    K: Tensor
    world_to_camera: Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3):
            raise ValueError(f"Camera.K must have shape (3, 3), got {tuple(self.K.shape)}")
        if tuple(self.world_to_camera.shape) != (4, 4):
            raise ValueError(f"Camera.world_to_camera must be (4, 4), got {tuple(self.world_to_camera.shape)}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera size must be positive, got {self.width}x{self.height}")

    @property
    def rotation(self) -> Tensor:
        """World-to-camera rotation [3,3]."""
        return self.world_to_camera[:3, :3]

    @property
    def translation(self) -> Tensor:
        """World-to-camera translation [3]."""
        return self.world_to_camera[:3, 3]

    @property
    def center(self) -> Tensor:
        """Camera centre in world coordinates [3]."""
        return -self.rotation.T @ self.translation

    @property
    def camera_to_world(self) -> Tensor:
        return torch.linalg.inv(self.world_to_camera)

    def to(self, device=None, dtype: torch.dtype | None = None) -> Camera:
        return Camera(self.K.to(device=device, dtype=dtype), self.world_to_camera.to(device=device, dtype=dtype),
                      self.width, self.height)

    def rescaled(self, width: int, height: int) -> Camera:
        """The same camera rendering an image of another size (intrinsics scaled per axis)."""
        scale = torch.tensor([width / self.width, height / self.height, 1.0], dtype=self.K.dtype,
                             device=self.K.device)
        return Camera(self.K * scale[:, None], self.world_to_camera.clone(), width, height)

    def reframed(self, width: int, height: int) -> Camera:
        """The same camera with an image plane of another size about the same centre: the focal lengths kept
        (no stretch), the principal point moved by half the change (whole pixels), so a portrait view becomes a
        landscape frame that crops its top and bottom and extends its sides (``reframe_image`` moves the pixels
        alike)."""
        if (width, height) == (self.width, self.height):
            return self
        K = self.K.clone()
        K[0, 2] += (width - self.width) // 2
        K[1, 2] += (height - self.height) // 2
        return Camera(K, self.world_to_camera.clone(), width, height)

    def as_record(self) -> dict:
        """The camera as JSON values (the names of a prepared scene's scene.json), for a record beside a product."""
        return {"intrinsics": self.K.tolist(), "world_to_camera": self.world_to_camera.tolist(),
                "size": [self.height, self.width]}

    @staticmethod
    def from_record(record: dict) -> Camera:
        """The camera :meth:`as_record` wrote."""
        height, width = record["size"]
        return Camera(torch.tensor(record["intrinsics"], dtype=torch.float32),
                      torch.tensor(record["world_to_camera"], dtype=torch.float32), int(width), int(height))

    @staticmethod
    def from_pose(K: Tensor, rotation: Tensor, center: Tensor, width: int, height: int) -> Camera:
        """Camera from a world-to-camera rotation and a world-space centre."""
        world_to_camera = torch.eye(4, dtype=rotation.dtype, device=rotation.device)
        world_to_camera[:3, :3] = rotation
        world_to_camera[:3, 3] = -rotation @ center
        return Camera(K.to(rotation), world_to_camera, width, height)

    @staticmethod
    def look_at(eye: Tensor, target: Tensor, up: Tensor, fov_x_deg: float | None = None, K: Tensor | None = None,
                width: int = 72, height: int = 48) -> Camera:
        """Camera at `eye` looking at `target`; give either a horizontal field of view or intrinsics `K`."""
        if (fov_x_deg is None) == (K is None):
            raise ValueError("Camera.look_at needs exactly one of fov_x_deg or K")
        eye, target = torch.as_tensor(eye, dtype=torch.float32), torch.as_tensor(target, dtype=torch.float32)
        rotation = look_at_rotation(eye, target, torch.as_tensor(up, dtype=torch.float32))
        intrinsics = intrinsics_from_fov(fov_x_deg, width, height) if K is None else K.to(torch.float32)
        return Camera.from_pose(intrinsics, rotation, eye, width, height)


def reframe_image(image: Tensor, width: int, height: int, fill: float = 0.0) -> Tensor:
    """``image`` [..., H, W] on the image plane of ``Camera.reframed(width, height)``: cropped or padded with
    ``fill`` by the same half-change on each side, so each pixel keeps its ray."""
    rows, cols = image.shape[-2:]
    top, left = (height - rows) // 2, (width - cols) // 2
    out = image.new_full((*image.shape[:-2], height, width), fill)
    kept_rows, kept_cols = min(rows, height), min(cols, width)
    out[..., max(0, top):max(0, top) + kept_rows, max(0, left):max(0, left) + kept_cols] = \
        image[..., max(0, -top):max(0, -top) + kept_rows, max(0, -left):max(0, -left) + kept_cols]
    return out
