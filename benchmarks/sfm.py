"""Structure-from-motion benchmark: how well tracegs-restore's photo path recovers known cameras, and how fast.

A procedural scene of the embedded benchmark (tracegs.data.synthetic's ground disc, cylinder wall, boxes and ball,
seen along its 300-degree orbit) is rendered at 320x240 from 30 cameras and handed to the photo path
(tracegs.data.sfm.reconstruct_photos: SIFT, exhaustive matching, incremental mapping, undistortion) with one
thread. The benchmark's own scenes are too smooth for SIFT at this size (their textures are 96 texels wide and
tiled three times around the wall, so views 120 degrees apart look alike), so this scene is textured for it: each
surface shows scikit-image's photographs at 256 texels, the ground a 2x2 mosaic and the wall a panorama of six,
none repeated, on Gaussians 2.5 cm apart.

Method, so the figures can be read correctly:
- the recovered camera centres are aligned to the true ones by a similarity transform (Umeyama's least squares,
  pycolmap.estimate_sim3d), over the registered cameras;
- rotation_error_deg: the largest angle between a registered camera's recovered orientation, carried into the true
  frame by the alignment, and its true orientation;
- center_error_rel: the largest distance between an aligned centre and the true one, over the scene's extent as
  3DGS defines it (1.1 x the largest distance of a true centre from their mean, tracegs.data.colmap.Scene.extent);
- registered_fraction: registered images over photos;
- sfm_seconds: wall time of reconstruct_photos, feature extraction to the undistorted scene folder, one thread.

Last line: JSON with those four figures, plus the photos, the mean reprojection error and the scene's extent.
Measured on a 2-core AMD EPYC VM (shared), torch 2.13.0+cpu, pycolmap 4.2.1: see docs/your_capture.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from tracegs.data import synthetic
from tracegs.data.colmap import Scene
from tracegs.data.config import SfmConfig, SyntheticConfig
from tracegs.data.sfm import reconstruct_photos
from tracegs.splat.cameras import Camera
from tracegs.splat.gaussians import GaussianModel

TEXELS = 256
SPACING = 0.025  # metres between surface Gaussians: about 3 pixels at the wall, from the orbit, at 320x240
WALL_RADIUS, WALL_HEIGHT = 3.2, 2.2
GROUND_MOSAIC = (("coins", "brick"), ("gravel", "grass"))
WALL_PANORAMA = ("astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "cat")


def photograph(name: str) -> np.ndarray:
    """A scikit-image photograph as float RGB [TEXELS, TEXELS, 3]."""
    import skimage.data
    from skimage.transform import resize

    image = np.asarray(getattr(skimage.data, name)(), dtype=np.float32)
    image = image / 255.0 if image.max() > 1.0 else image
    image = np.repeat(image[..., None], 3, axis=2) if image.ndim == 2 else image[..., :3]
    return resize(image, (TEXELS, TEXELS), anti_aliasing=True).astype(np.float32)


def mosaic(rows) -> np.ndarray:
    return np.concatenate([np.concatenate([photograph(name) for name in row], axis=1) for row in rows], axis=0)


def textured_scene(ground: tuple = GROUND_MOSAIC, wall: tuple = WALL_PANORAMA) -> GaussianModel:
    """The embedded benchmark's shapes with untiled photographs (module docstring): the ground a mosaic of
    ``ground``'s rows, the wall a panorama of ``wall`` and the objects its second to fourth photographs."""
    rng = np.random.default_rng(0)
    disc = synthetic.ground_disc(WALL_RADIUS, SPACING, photograph("gravel"), rng)
    disc.rgb = synthetic.sample_texture(mosaic(ground), (disc.xyz[:, :2] + WALL_RADIUS) / (2 * WALL_RADIUS) * 0.999)
    backdrop = synthetic.cylinder_wall(WALL_RADIUS, WALL_HEIGHT, SPACING, photograph("gravel"))
    around = np.mod(np.arctan2(backdrop.xyz[:, 1], backdrop.xyz[:, 0]), 2 * math.pi) / (2 * math.pi)
    backdrop.rgb = synthetic.sample_texture(mosaic([wall]), np.stack([around / 1.0001,
                                                                      backdrop.xyz[:, 2] / WALL_HEIGHT], 1))
    objects = [synthetic.box(np.array([0.5, 0.3, 0.0]), 0.6, SPACING, photograph(wall[1])),
               synthetic.box(np.array([-0.6, -0.2, 0.0]), 0.5, SPACING, photograph(wall[2])),
               synthetic.sphere(np.array([0.0, -0.8, 0.3]), 0.3, SPACING, photograph(wall[3]))]
    return synthetic.gaussians_from_surfaces([disc, backdrop, *objects])


def orbit(views: int, width: int = 320, height: int = 240, arc_deg: float = 300.0, seed: int = 3) -> list[Camera]:
    """The embedded benchmark's orbit camera path (tracegs.data.synthetic.camera_path) at a size SIFT can use."""
    cfg = SyntheticConfig(num_views=views, width=width, height=height, orbit_arc_deg=arc_deg)
    return synthetic.camera_path(cfg, "orbit", seed)


def render_frames(model: GaussianModel, cameras: list[Camera]) -> list[np.ndarray]:
    """uint8 RGB frames [H, W, 3] of ``model`` at ``cameras``, on a black background."""
    return [(image.permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
            for image in synthetic.render_images(model, cameras, [0.0, 0.0, 0.0])]


def write_photos(folder: Path, model: GaussianModel, cameras: list[Camera],
                 prefix: str = "photo") -> dict[str, Camera]:
    """Photos of ``model`` at ``cameras`` as PNGs in ``folder``; returns each photo's true camera by name."""
    folder.mkdir(parents=True, exist_ok=True)
    truth = {}
    for index, (frame, camera) in enumerate(zip(render_frames(model, cameras), cameras)):
        name = f"{prefix}_{index:03d}.png"
        Image.fromarray(frame).save(folder / name)
        truth[name] = camera
    return truth


def camera_errors(scene: Path, truth: dict[str, Camera]) -> dict[str, float]:
    """The reconstruction in ``scene/sparse/0`` against the true cameras (module docstring's measures)."""
    import pycolmap  # after PIL and torch (bundled zlib, tracegs.data.colmap)

    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    images = sorted(model.images.values(), key=lambda image: image.name)
    recovered = np.stack([image.projection_center() for image in images])
    true_centres = np.stack([truth[image.name].center.numpy() for image in images]).astype(np.float64)
    true_from_sfm = pycolmap.estimate_sim3d(recovered, true_centres)
    aligned = np.stack([true_from_sfm * centre for centre in recovered])
    cameras = list(truth.values())
    extent = Scene("truth", scene, cameras, [], [], torch.zeros(0, 3), torch.zeros(0, 3),
                   torch.zeros(0, len(cameras), dtype=torch.bool)).extent()
    alignment = true_from_sfm.rotation.matrix()
    angles = []
    for image in images:
        difference = truth[image.name].rotation.double().numpy() @ alignment @ image.cam_from_world().rotation.matrix().T
        angles.append(math.degrees(math.acos(float(np.clip((np.trace(difference) - 1) / 2, -1.0, 1.0)))))
    return {"registered_fraction": len(images) / len(truth), "rotation_error_deg": max(angles),
            "center_error_rel": float(np.linalg.norm(aligned - true_centres, axis=1).max() / extent),
            "extent": extent}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--photos", type=int, default=30)
    args = parser.parse_args()
    torch.set_num_threads(1)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with tempfile.TemporaryDirectory() as tmp:
        capture = Path(tmp) / "capture"
        truth = write_photos(capture, textured_scene(), orbit(args.photos))
        started = time.perf_counter()
        scene = reconstruct_photos(capture, SfmConfig(dir=str(Path(tmp) / "captures"), threads=1), views=3,
                                   test_every=8)
        seconds = time.perf_counter() - started
        figures = camera_errors(scene, truth)
        record = json.loads((scene / "sfm.json").read_text())
    figures = {"photos": args.photos, **figures, "sfm_seconds": round(seconds, 2),
               "mean_reprojection_error_px": record["mean_reprojection_error"]}
    print(f"{args.photos} photos at 320x240: registered {figures['registered_fraction']:.0%}, "
          f"rotation error <= {figures['rotation_error_deg']:.3f} deg, centre error <= "
          f"{100 * figures['center_error_rel']:.3f}% of the extent ({figures['extent']:.2f}), "
          f"mean reprojection error {figures['mean_reprojection_error_px']:.2f} px, {seconds:.1f} s")
    print(json.dumps({key: round(value, 4) if isinstance(value, float) else value for key, value in figures.items()}))


if __name__ == "__main__":
    main()
