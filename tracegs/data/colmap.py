"""COLMAP scenes: loading (pycolmap), downscaled image folders, normalisation, dataset presets, writing.

pycolmap bundles its own zlib; importing it before PIL/torch can crash a later PNG write, so it is
imported inside the functions that need it, after PIL and torch are loaded.
"""

from __future__ import annotations

import csv
import io
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from tracegs.data.config import SceneSourceConfig, SourcePreset
from tracegs.data.images import read_rgb, resize
from tracegs.errors import ConfigError, InputFileError, plain_name_problem
from tracegs.io import atomic_directory
from tracegs.location import CONF_DIR
from tracegs.processes import import_keeping_sigterm
from tracegs.splat.cameras import Camera

log = logging.getLogger(__name__)

SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
RADIAL_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE",
                 "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE", "FOV", "RAD_TAN_THIN_PRISM_FISHEYE")

# Folder names per dataset layout. Mip-NeRF 360 ships images_{2,4,8} next to sparse/0; the DL3DV
# benchmark's COLMAP export and NeRFBusters' captures use the same sparse/0 + images_N layout. NeRFBusters
# evaluates on its second capture, whose frames are named "frame_2_*".
PRESETS: dict[str, dict[str, str | None]] = {
    "synthetic": {"image_dir": "images", "sparse_dir": "sparse/0", "test_prefix": None},
    "mipnerf360": {"image_dir": "images_4", "sparse_dir": "sparse/0", "test_prefix": None},
    "dl3dv": {"image_dir": "images_4", "sparse_dir": "sparse/0", "test_prefix": None},
    "nerfbusters": {"image_dir": "images_2", "sparse_dir": "sparse/0", "test_prefix": "frame_2_"},
    "custom": {"image_dir": "images", "sparse_dir": "sparse/0", "test_prefix": None},
}


class SceneFormatError(ValueError):
    """A scene directory does not hold a usable COLMAP model and image folder."""


@dataclass
class Scene:
    """One posed multi-view scene, images loaded lazily from ``image_paths``.

    ``points``/``colors`` are the SfM points (colours in [0,1]); ``visibility[p, i]`` says whether point
    ``p`` is observed in image ``i`` (its COLMAP track), so a view set can be initialised only from the
    points that its own views would triangulate.
    """

    name: str
    root: Path
    cameras: list[Camera]
    image_names: list[str]
    image_paths: list[Path]
    points: torch.Tensor
    colors: torch.Tensor
    visibility: torch.Tensor
    caption: str | None = None
    # Normalisation applied by ``normalize_scene``: x_normalised = (x_stored - world_offset) / world_scale.
    world_offset: torch.Tensor = field(default_factory=lambda: torch.zeros(3))
    world_scale: float = 1.0

    def __len__(self) -> int:
        return len(self.cameras)

    def load_image(self, index: int) -> torch.Tensor:
        """Image ``index`` as float [3, H, W] in [0, 1] (any supported mode, upright: ``data.images``), resized
        to its camera's size if needed."""
        camera = self.cameras[index]
        array = read_rgb(self.image_paths[index])
        if array.shape[:2] != (camera.height, camera.width):
            array = resize(array, camera.width, camera.height)
        return torch.from_numpy(array).permute(2, 0, 1).contiguous()

    def extent(self) -> float:
        """3DGS's scene extent: 1.1 x the largest camera-centre distance from their mean."""
        centres = torch.stack([c.center for c in self.cameras])
        return float(1.1 * (centres - centres.mean(0)).norm(dim=-1).max().clamp_min(1e-6))

    def points_seen_by(self, views: list[int], min_views: int) -> tuple[torch.Tensor, torch.Tensor]:
        """SfM points observed by at least ``min_views`` of ``views`` (what those views triangulate)."""
        keep = self.visibility[:, views].sum(dim=1) >= min_views
        return self.points[keep], self.colors[keep]


def preset_dirs(cfg: SceneSourceConfig) -> tuple[str, str, str | None]:
    if cfg.preset not in PRESETS:
        raise SceneFormatError(f"source.preset={cfg.preset!r} unknown; choose one of {sorted(PRESETS)}")
    preset = PRESETS[cfg.preset]
    return cfg.image_dir or preset["image_dir"], cfg.sparse_dir or preset["sparse_dir"], preset["test_prefix"]


def read_scene_list(path: str, field: str) -> list[str]:
    """Scene names of a list file: one a line (blank lines and ``#`` comments ignored), or a ``.csv`` table whose
    ``hash`` column names them, as DL3DV-Benchmark publishes its scenes (``benchmark-meta.csv``: a header row,
    then one row a scene, its folder named by the hash). A relative path that does not exist from the working
    directory is read from the config tree, where the published benchmark lists ship (``conf/data/scenes/``)."""
    file = Path(path)
    if not file.is_file() and not file.is_absolute():
        file = Path(CONF_DIR) / path
    if not file.is_file():
        raise FileNotFoundError(f"{field}={path!r}: scene list not found")
    if file.suffix == ".csv":
        table = csv.DictReader(io.StringIO(file.read_text(encoding="utf-8-sig"), newline=""))
        if "hash" not in (table.fieldnames or []):
            raise InputFileError(file, f"no 'hash' column in its header {table.fieldnames}",
                                 f"name the scene folders in a 'hash' column, or one a line in a .txt file, for {field}")
        names, first_line = [(row["hash"] or "").strip() for row in table], 2
    else:
        names, first_line = [line.split("#", 1)[0].strip() for line in file.read_text().splitlines()], 1
    for number, name in enumerate(names, first_line):
        problem = plain_name_problem(name) if name else None
        if problem:
            raise InputFileError(file, f"line {number}: {name!r} {problem}",
                                 f"list plain scene names (folders under the scene root) in {field}")
    return [name for name in names if name]


def require_held_out(scenes: list[str], training: list[str], field: str) -> None:
    """Refuse to evaluate a scene the restorer was trained on (``field`` names the training list)."""
    shared = sorted(set(scenes) & set(training))
    if shared:
        raise SceneFormatError(f"{field} names training scenes {shared[:5]} (on source.train_list); evaluation "
                               "needs held-out scenes")


# Benchmarks of which every scene is a test scene (out of domain, Table 2): their published scene lists ship
# with the configs. DL3DV's benchmark scenes are the user's source.test_list (README: the paper's 28 are not named).
BENCHMARK_LISTS = {
    SourcePreset.mipnerf360: ("Mip-NeRF 360", "data/scenes/mipnerf360_benchmark.txt"),
    SourcePreset.nerfbusters: ("NeRFBusters", "data/scenes/nerfbusters_benchmark.txt"),
}


def require_not_benchmark(names: list[str], cfg: SceneSourceConfig) -> None:
    """Refuse to train on a benchmark scene, before any work: a scene of this dataset's published benchmark, or
    one on ``source.test_list`` (the DL3DV-Benchmark scenes)."""
    benchmarks = []
    if cfg.preset in BENCHMARK_LISTS:
        label, path = BENCHMARK_LISTS[cfg.preset]
        benchmarks.append((f"a {label} benchmark scene (conf/{path})", read_scene_list(path, "benchmark list")))
    if cfg.test_list is not None:
        benchmarks.append((f"on source.test_list={cfg.test_list!r}", read_scene_list(cfg.test_list,
                                                                                     "source.test_list")))
    for label, listed in benchmarks:
        shared = [name for name in names if name in set(listed)]
        if shared:
            raise ConfigError("data.source.train_list", f"scene {shared[0]!r} is {label}: benchmark scenes are "
                                                        "evaluated, never trained on; list the training scenes in "
                                                        "data.source.train_list (or data.source.scenes)")


def require_training_source(cfg: SceneSourceConfig) -> None:
    """The training scenes a config names hold no benchmark scene, checked from the config and its lists before
    any model is loaded or scene read. Without a training list every scene under the root would be trained on:
    refused where the root holds benchmark scenes (a benchmark-only dataset, or a root with a test list)."""
    if cfg.scenes is None and cfg.train_list is None:
        if cfg.preset in BENCHMARK_LISTS or cfg.test_list is not None:
            held = (f"{BENCHMARK_LISTS[cfg.preset][0]} benchmark scenes" if cfg.preset in BENCHMARK_LISTS
                    else f"the benchmark scenes of source.test_list={cfg.test_list!r}")
            raise ConfigError("data.source.train_list", f"null, so every scene under {cfg.root} would be trained "
                                                        f"on, {held} included; list the training scenes in "
                                                        "data.source.train_list (or data.source.scenes)")
        return
    names = list(cfg.scenes) if cfg.scenes is not None else read_scene_list(cfg.train_list, "source.train_list")
    require_not_benchmark(names, cfg)


def training_scenes(cfg: SceneSourceConfig) -> list[str]:
    """The scenes named by ``cfg.train_list`` (none when it is unset)."""
    return [] if cfg.train_list is None else read_scene_list(cfg.train_list, "source.train_list")


def list_scenes(cfg: SceneSourceConfig, split: str = "train") -> list[str]:
    """Scene names of ``split`` ("train": prepare / training, "test": evaluation): ``cfg.scenes``, else the
    split's list file, else every directory under ``cfg.root`` holding a sparse model. With both lists set,
    a scene on both is refused, so evaluation never runs on a scene the restorer was trained on."""
    if split not in ("train", "test"):
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    names = _split_scenes(cfg, split)
    if split == "train":
        require_not_benchmark(names, cfg)
    return names


def _split_scenes(cfg: SceneSourceConfig, split: str) -> list[str]:
    if cfg.scenes is not None:
        return list(cfg.scenes)
    lists = {"train": cfg.train_list, "test": cfg.test_list}
    if lists["test"] is not None:
        require_held_out(read_scene_list(lists["test"], "source.test_list"), training_scenes(cfg),
                         f"source.test_list={lists['test']!r}")
    root = Path(cfg.root)
    if lists[split] is not None:
        names = read_scene_list(lists[split], f"source.{split}_list")
        missing = [n for n in names if not (root / n).is_dir()]
        if missing:
            raise SceneFormatError(f"source.{split}_list={lists[split]!r}: {missing[:5]} not under {root}")
        return names
    if not root.is_dir():
        raise SceneFormatError(f"source.root {root} does not exist")
    _, sparse_dir, _ = preset_dirs(cfg)
    folders = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    lacking = [p.name for p in folders if not (p / sparse_dir).is_dir()]
    if lacking:
        raise InputFileError(root / lacking[0] / sparse_dir,
                             f"scene folder without a COLMAP reconstruction ({len(lacking)} of {len(folders)} "
                             f"scene folders lack {sparse_dir}: {lacking[:5]})",
                             "run COLMAP on it, move it out of source.root, or list the scenes to use in "
                             "data.source.scenes")
    return [p.name for p in folders]


def camera_from_colmap(colmap_camera, cam_from_world: np.ndarray, source: Path) -> Camera:
    """A ``Camera`` from a pycolmap camera and its 3x4 cam_from_world matrix (both OpenCV convention)."""
    model = colmap_camera.model.name
    params = [float(p) for p in colmap_camera.params]
    if model == "PINHOLE":
        fx, fy, cx, cy = params
    elif model == "SIMPLE_PINHOLE":
        fx, cx, cy = params
        fy = fx
    elif model in RADIAL_MODELS:
        raise SceneFormatError(
            f"{source}: camera model {model} has lens distortion; undistort the images first "
            "(colmap image_undistorter) to get a PINHOLE model"
        )
    else:
        raise SceneFormatError(f"{source}: unsupported camera model {model} (need {SUPPORTED_MODELS})")
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32)
    w2c = torch.eye(4, dtype=torch.float32)
    w2c[:3, :4] = torch.from_numpy(np.asarray(cam_from_world, dtype=np.float32))
    return Camera(K=K, world_to_camera=w2c, width=int(colmap_camera.width), height=int(colmap_camera.height))


def normalize_scene(scene: Scene) -> Scene:
    """Similarity transform x' = (x - c) / r: camera centres to mean zero and radius 1/1.1.

    Rotations stay orthonormal because the world scale is folded into the camera translation:
    X_cam' = X_cam / r = R x' + (R c + t) / r.
    """
    centres = torch.stack([c.center for c in scene.cameras])
    centre = centres.mean(0)
    radius = 1.1 * float((centres - centre).norm(dim=-1).max().clamp_min(1e-6))
    cameras = []
    for camera in scene.cameras:
        w2c = camera.world_to_camera.clone()
        w2c[:3, 3] = (w2c[:3, :3] @ centre + w2c[:3, 3]) / radius
        cameras.append(replace(camera, world_to_camera=w2c))
    return replace(scene, cameras=cameras, points=(scene.points - centre) / radius, world_offset=centre,
                   world_scale=radius)


def same_aspect_ratio(size: tuple[int, int], other: tuple[int, int]) -> bool:
    """Whether two (width, height) sizes are one picture at two scales, up to the pixel a downscale rounds."""
    (w, h), (W, H) = size, other
    return abs(w * H - h * W) <= max(W, H)


def camera_for_image(camera: Camera, path: Path, sparse: Path) -> Camera:
    """``camera`` for the image at ``path`` as decoded (all of it, so a truncated, corrupt or unsupported file
    fails here, at scene load, rather than in the middle of a fit after other products were written).

    Downscaled folders (images_4, ...) keep COLMAP's full-resolution intrinsics: an image of the same aspect
    ratio gets them scaled; one of another aspect ratio (rotated, cropped, another photograph) is refused.
    """
    height, width = read_rgb(path).shape[:2]
    if (width, height) == (camera.width, camera.height):
        return camera
    if not same_aspect_ratio((width, height), (camera.width, camera.height)):
        raise InputFileError(path, f"image is {width}x{height} but its camera in {sparse} is "
                                   f"{camera.width}x{camera.height} (another aspect ratio)",
                             "use the images the COLMAP model was made from, or reconstruct these")
    return camera.rescaled(width, height)


def frame_size(cfg: SceneSourceConfig, width: int, height: int) -> tuple[int, int]:
    """The (width, height) an image of ``width`` x ``height`` is loaded at: downsized to ``cfg.long_side`` on its
    longer side with its aspect ratio kept (never enlarged: that adds no detail), else ``cfg.width`` x
    ``cfg.height`` (each None = as stored)."""
    if cfg.long_side is not None:
        scale = min(1.0, cfg.long_side / max(width, height))
        return max(1, round(width * scale)), max(1, round(height * scale))
    return cfg.width or width, cfg.height or height


def load_scene(cfg: SceneSourceConfig, name: str) -> Scene:
    """Load scene ``name`` under ``cfg.root``; every listed image must exist in the image folder."""
    # lazily, after PIL and torch (bundled zlib, see module docstring)
    pycolmap = import_keeping_sigterm("pycolmap")

    image_dir, sparse_dir, _ = preset_dirs(cfg)
    root = Path(cfg.root) / name
    sparse = root / sparse_dir
    images_root = root / image_dir
    if not sparse.is_dir():
        raise SceneFormatError(f"{sparse}: COLMAP model directory not found")
    if not images_root.is_dir():
        raise FileNotFoundError(f"{images_root}: image folder not found")
    try:
        reconstruction = pycolmap.Reconstruction(str(sparse))
    except Exception as error:  # pycolmap raises plain RuntimeError/ValueError on malformed models
        raise SceneFormatError(f"{sparse}: cannot read COLMAP model ({error})") from error
    images = sorted(reconstruction.images.values(), key=lambda im: im.name)
    if not images:
        raise SceneFormatError(f"{sparse}: the model has no registered images")
    paths = [images_root / im.name for im in images]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"{missing[0]}: listed in {sparse} but absent ({len(missing)} missing)")
    cameras = []
    scaled: set[tuple[tuple[int, int], tuple[int, int]]] = set()
    for image, path in zip(images, paths):
        calibrated = camera_from_colmap(image.camera, image.cam_from_world().matrix(), sparse)
        camera = camera_for_image(calibrated, path, sparse)
        if camera is not calibrated:
            scaled.add(((calibrated.width, calibrated.height), (camera.width, camera.height)))
        width, height = frame_size(cfg, camera.width, camera.height)
        if (width, height) != (camera.width, camera.height):
            camera = camera.rescaled(width, height)
        cameras.append(camera)
    for (W, H), (w, h) in sorted(scaled):
        log.info("%s: images of %dx%d with cameras of %dx%d in %s: intrinsics scaled to the images",
                 name, w, h, W, H, sparse)
    index_of = {im.image_id: i for i, im in enumerate(images)}
    point_ids = sorted(reconstruction.points3D)
    points = np.zeros((len(point_ids), 3), dtype=np.float32)
    colors = np.zeros((len(point_ids), 3), dtype=np.float32)
    visibility = torch.zeros(len(point_ids), len(images), dtype=torch.bool)
    for row, pid in enumerate(point_ids):
        point = reconstruction.points3D[pid]
        points[row] = point.xyz
        colors[row] = np.asarray(point.color, dtype=np.float32) / 255.0
        for element in point.track.elements:
            if element.image_id in index_of:
                visibility[row, index_of[element.image_id]] = True
    caption_file = root / "caption.txt"
    scene = Scene(
        name=name,
        root=root,
        cameras=cameras,
        image_names=[im.name for im in images],
        image_paths=paths,
        points=torch.from_numpy(points),
        colors=torch.from_numpy(colors),
        visibility=visibility,
        caption=caption_file.read_text().strip() if caption_file.is_file() else None,
    )
    return normalize_scene(scene) if cfg.normalize else scene


def test_indices_for(cfg: SceneSourceConfig, scene: Scene) -> list[int] | None:
    """Test views named by the preset (NeRFBusters' second capture); None = the every-8th rule."""
    _, _, prefix = preset_dirs(cfg)
    if prefix is None:
        return None
    return [i for i, n in enumerate(scene.image_names) if n.startswith(prefix)]


def write_colmap_model(
    path: Path,
    cameras: list[Camera],
    image_names: list[str],
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    tracks: list[list[tuple[int, np.ndarray]]] | None = None,
) -> None:
    """Write a binary COLMAP model (one PINHOLE camera per image) with pycolmap.

    ``tracks[p]`` lists ``(image_index, xy)`` observations of point ``p``. The model is written to a
    temporary sibling directory and renamed into place, so a killed run never leaves half a model.
    """
    pycolmap = import_keeping_sigterm("pycolmap")  # lazily, after PIL and torch (bundled zlib)

    reconstruction = pycolmap.Reconstruction()
    keypoints: list[list[np.ndarray]] = [[] for _ in cameras]
    point_refs: list[list[tuple[int, int]]] = []
    for track in tracks or []:
        refs = []
        for image_index, xy in track:
            refs.append((image_index, len(keypoints[image_index])))
            keypoints[image_index].append(np.asarray(xy, dtype=np.float64))
        point_refs.append(refs)
    for i, (camera, name) in enumerate(zip(cameras, image_names)):
        K = camera.K.double().numpy()
        reconstruction.add_camera_with_trivial_rig(
            pycolmap.Camera(model="PINHOLE", width=camera.width, height=camera.height,
                            params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=i + 1)
        )
        kp = np.stack(keypoints[i]) if keypoints[i] else np.zeros((0, 2))
        image = pycolmap.Image(name=name, keypoints=kp, camera_id=i + 1, image_id=i + 1)
        w2c = camera.world_to_camera.double().numpy()
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        reconstruction.add_image_with_trivial_frame(image, pose)
    for p in range(0 if points is None else len(points)):
        track = pycolmap.Track()
        for image_index, point2d_index in point_refs[p] if p < len(point_refs) else []:
            track.add_element(image_index + 1, point2d_index)
        color = np.clip(np.asarray(colors[p]) * 255.0 if colors is not None else np.zeros(3), 0, 255)
        reconstruction.add_point3D(np.asarray(points[p], dtype=np.float64), track, color.astype(np.uint8))
    with atomic_directory(path) as staging:
        reconstruction.write(str(staging))
