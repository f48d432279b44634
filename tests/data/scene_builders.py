"""Builders of tiny COLMAP scenes (written with pycolmap) shared by the data tests."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from tracegs.data.colmap import write_colmap_model
from tracegs.data.config import PrepareConfig, SceneSourceConfig, SyntheticConfig
from tracegs.splat.cameras import Camera
from tracegs.splat.config import GaussianFitConfig, TrajectoryConfig


def ring_cameras(n: int, width: int = 36, height: int = 24) -> list[Camera]:
    """Cameras on a circle around the origin with slightly different (non-square) intrinsics each."""
    cameras = []
    for i in range(n):
        angle = 2 * math.pi * i / n
        eye = torch.tensor([3.0 * math.cos(angle), 3.0 * math.sin(angle), 1.0 + 0.1 * i])
        camera = Camera.look_at(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]), fov_x_deg=50.0 + i,
                                width=width, height=height)
        K = camera.K.clone()
        K[1, 1] *= 1.05  # fy != fx so PINHOLE's four parameters are all exercised
        K[0, 2] += 0.25
        cameras.append(Camera(K, camera.world_to_camera, width, height))
    return cameras


def write_scene(root: Path, n: int = 16, image_dir: str = "images", image_scale: int = 1,
                points: int = 50) -> tuple[Path, list[Camera]]:
    """A scene directory with ``n`` images (in ``image_dir``, sized camera/``image_scale``) and sparse/0 with
    ``points`` SfM points, each seen by images 0, 3, 6, ..."""
    cameras = ring_cameras(n)
    names = [f"img_{i:03d}.png" for i in range(n)]
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, (points, 3))
    tracks = [[(i, np.array([1.0 + p % 30, 1.0 + i])) for i in range(0, n, 3)] for p in range(points)]
    write_colmap_model(root / "sparse" / "0", cameras, names, xyz, rng.uniform(0, 1, (points, 3)), tracks)
    (root / image_dir).mkdir(parents=True)
    for i, name in enumerate(names):
        w, h = cameras[i].width // image_scale, cameras[i].height // image_scale
        Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)).save(root / image_dir / name)
    return root, cameras


def tiny_configs(tmp: Path) -> tuple[SyntheticConfig, SceneSourceConfig, PrepareConfig]:
    """One 12-view synthetic scene at 32x48, 16-iteration fits, two 5-frame clips: seconds on a CPU."""
    synthetic = SyntheticConfig(root=str(tmp / "synthetic"), train_seeds=[0], test_seeds=[], num_views=12,
                                height=32, width=48, num_objects=2, gaussians_per_unit_area=60.0, init_points=200)
    source = SceneSourceConfig(root=synthetic.root, preset="synthetic")
    prepare = PrepareConfig(cache_dir=str(tmp / "cache"), work_dir=str(tmp / "work"), student_views=[3],
                            dense_views=[6, None], student_snapshots=[8],
                            fit=GaussianFitConfig(iterations=16, snapshot_iters=[8, 16]),
                            clips_per_scene=2, frames_per_clip=5, workers=1,
                            trajectory=TrajectoryConfig(frames_per_clip=5),
                            store_frames=True)  # the data tests also score these clips as held-out ones
    return synthetic, source, prepare


def all_files(root: Path) -> dict[str, int]:
    """Modification time of every file under ``root`` (to prove a rerun wrote nothing)."""
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}


def differing_files(expected: Path, actual: Path) -> list[str]:
    """Files (relative paths) that are missing, extra or differ in bytes between two folders."""
    files = {str(p.relative_to(root)) for root in (expected, actual) for p in root.rglob("*") if p.is_file()}
    return sorted(f for f in files if not ((expected / f).is_file() and (actual / f).is_file()
                                           and (expected / f).read_bytes() == (actual / f).read_bytes()))
