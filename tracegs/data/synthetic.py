"""The embedded synthetic benchmark: procedural Gaussian scenes written as COLMAP datasets.

Each seed gives one scene: a textured ground disc, a backdrop (a cylinder wall for orbit paths, a plane
for forward-facing paths) and a few textured boxes and spheres, all made of opaque isotropic Gaussians
coloured from the photographs scikit-image ships. Ground-truth images are rendered along the scene's
camera path and written with a COLMAP model (``sparse/0``) so the same loader reads real and synthetic
scenes. The ground-truth Gaussians are kept (``gt_scene.ply``), so ground truth can be rendered at any
pose (``render_ground_truth``), e.g. along the trajectories of the paired clips.
"""

from __future__ import annotations

import json
import math
import shutil
from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from rich.progress import Progress

from tracegs.data.colmap import Scene, write_colmap_model
from tracegs.data.config import SyntheticConfig, overlapping_seeds, split_seeds
from tracegs.io import atomic_directory
from tracegs.processes import run_units
from tracegs.splat.cameras import Camera
from tracegs.splat.gaussians import NUM_SH_REST, SH_C0, GaussianModel, rgb_to_sh_dc
from tracegs.splat.ply import load_ply, save_ply
from tracegs.splat.render import render

GROUND_TEXTURES = ("grass", "gravel", "brick")
BACKDROP_TEXTURES = ("coffee", "astronaut", "chelsea", "rocket", "hubble_deep_field", "cat")
OBJECT_TEXTURES = ("brick", "text", "coins", "camera", "moon", "page", "colorwheel", "immunohistochemistry",
                   "clock", "coffee")
# Photographs of scikit-image's that load without a download and texture none of the benchmark's scenes: the
# pretraining scenes' other statistics (data.synthetic.pretrain_textures).
OTHER_TEXTURES = ("retina", "microaneurysms", "logo", "cell", "checkerboard", "horse", "shepp_logan_phantom")
TEXTURES = frozenset(GROUND_TEXTURES + BACKDROP_TEXTURES + OBJECT_TEXTURES + OTHER_TEXTURES)
GT_PLY = "gt_scene.ply"
TEXTURE_SIZE = 96  # textures are band-limited first: a Gaussian samples one colour at its centre
OPAQUE_LOGIT = 5.0


def scene_name(seed: int) -> str:
    return f"scene_{seed:03d}"


def benchmark_scene_names(cfg: SyntheticConfig, split: str) -> list[str]:
    """Scene names of one split's seeds."""
    return [scene_name(s) for s in split_seeds(cfg, split)]


def load_texture(name: str, rng: np.random.Generator) -> np.ndarray:
    """A scikit-image photograph as float RGB [TEXTURE_SIZE, TEXTURE_SIZE, 3]; greyscale ones get a tint."""
    import skimage.data
    from skimage.transform import resize

    image = np.asarray(getattr(skimage.data, name)(), dtype=np.float32)
    image = image / 255.0 if image.max() > 1.0 else image
    if image.ndim == 2:
        tint = 0.45 + 0.55 * rng.random(3)
        image = image[..., None] * tint[None, None, :]
    image = image[..., :3]
    return resize(image, (TEXTURE_SIZE, TEXTURE_SIZE), anti_aliasing=True).astype(np.float32)


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Colours at texture coordinates ``uv`` in [0,1]^2 (wrapping), nearest texel."""
    size = texture.shape[0]
    ij = np.floor(np.mod(uv, 1.0) * size).astype(int).clip(0, size - 1)
    return texture[size - 1 - ij[:, 1], ij[:, 0]]


@dataclass
class Surface:
    """Gaussian centres, colours and a shared radius for one textured shape."""

    xyz: np.ndarray
    rgb: np.ndarray
    radius: float


def ground_disc(radius: float, spacing: float, texture: np.ndarray, rng: np.random.Generator) -> Surface:
    steps = np.arange(-radius, radius, spacing)
    x, y = np.meshgrid(steps, steps, indexing="ij")
    xy = np.stack([x.ravel(), y.ravel()], 1) + rng.uniform(-0.3, 0.3, (x.size, 2)) * spacing
    xy = xy[np.linalg.norm(xy, axis=1) < radius]
    xyz = np.concatenate([xy, np.zeros((len(xy), 1))], 1)
    return Surface(xyz, sample_texture(texture, xy / 2.0), 0.7 * spacing)


def cylinder_wall(radius: float, height: float, spacing: float, texture: np.ndarray) -> Surface:
    n_around = int(2 * math.pi * radius / spacing)
    n_up = int(height / spacing)
    theta, z = np.meshgrid(np.linspace(0, 2 * math.pi, n_around, endpoint=False),
                           (np.arange(n_up) + 0.5) * spacing, indexing="ij")
    xyz = np.stack([radius * np.cos(theta.ravel()), radius * np.sin(theta.ravel()), z.ravel()], 1)
    # The photograph is repeated three times around the wall so every side shows recognisable content.
    uv = np.stack([3 * theta.ravel() / (2 * math.pi), z.ravel() / height], 1)
    return Surface(xyz, sample_texture(texture, uv), 0.75 * spacing)


def backdrop_plane(y: float, half_width: float, height: float, spacing: float, texture: np.ndarray) -> Surface:
    x, z = np.meshgrid(np.arange(-half_width, half_width, spacing), (np.arange(int(height / spacing)) + 0.5) * spacing,
                       indexing="ij")
    xyz = np.stack([x.ravel(), np.full(x.size, y), z.ravel()], 1)
    uv = np.stack([(x.ravel() + half_width) / (2 * half_width), z.ravel() / height], 1)
    return Surface(xyz, sample_texture(texture, uv), 0.75 * spacing)


def box(center: np.ndarray, size: float, spacing: float, texture: np.ndarray) -> Surface:
    """Five faces of a cube standing on the ground (the bottom face is never seen)."""
    ticks = (np.arange(int(size / spacing)) + 0.5) / int(size / spacing)
    a, b = (g.ravel() for g in np.meshgrid(ticks, ticks, indexing="ij"))
    faces = []
    for axis in range(3):
        for side in (0.0, 1.0):
            if axis == 2 and side == 0.0:
                continue
            local = np.zeros((a.size, 3))
            others = [i for i in range(3) if i != axis]
            local[:, axis], local[:, others[0]], local[:, others[1]] = side, a, b
            faces.append((local, np.stack([a, b], 1)))
    local = np.concatenate([f[0] for f in faces])
    uv = np.concatenate([f[1] for f in faces])
    xyz = center[None] + (local - np.array([0.5, 0.5, 0.0])) * size
    return Surface(xyz, sample_texture(texture, uv), 0.7 * spacing)


def sphere(center: np.ndarray, radius: float, spacing: float, texture: np.ndarray) -> Surface:
    """Fibonacci-lattice sphere, texture mapped by longitude/latitude."""
    n = max(int(4 * math.pi * radius**2 / spacing**2), 16)
    i = np.arange(n) + 0.5
    polar = np.arccos(1 - 2 * i / n)
    azimuth = math.pi * (1 + 5**0.5) * i
    direction = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1)
    uv = np.stack([np.mod(azimuth, 2 * math.pi) / (2 * math.pi), polar / math.pi], 1)
    return Surface(center[None] + radius * direction, sample_texture(texture, uv), 0.7 * spacing)


def gaussians_from_surfaces(surfaces: list[Surface]) -> GaussianModel:
    xyz = torch.from_numpy(np.concatenate([s.xyz for s in surfaces])).float()
    rgb = torch.from_numpy(np.concatenate([s.rgb for s in surfaces])).float().clamp(0, 1)
    radius = torch.from_numpy(np.concatenate([np.full(len(s.xyz), s.radius) for s in surfaces])).float()
    n = xyz.shape[0]
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    return GaussianModel(
        means=xyz, quats=quats, log_scales=radius.log()[:, None].repeat(1, 3),
        opacity_logits=torch.full((n,), OPAQUE_LOGIT), sh_dc=rgb_to_sh_dc(rgb)[:, None, :],
        sh_rest=torch.zeros(n, NUM_SH_REST, 3),
    )


@dataclass(frozen=True)
class Palette:
    """The photographs a scene's ground, backdrop and objects are textured with."""

    grounds: tuple[str, ...] = GROUND_TEXTURES
    backdrops: tuple[str, ...] = BACKDROP_TEXTURES
    objects: tuple[str, ...] = OBJECT_TEXTURES


def scene_palette(seed: int, cfg: SyntheticConfig) -> Palette:
    """Scene ``seed``'s textures: a pretraining scene draws every surface from ``cfg.pretrain_textures`` when set
    (variant A's scenes of other statistics, as GSFixer's training scenes are not TRACE-GS's), any other the
    benchmark's lists."""
    if cfg.pretrain_textures and seed in cfg.pretrain_seeds:
        names = tuple(cfg.pretrain_textures)
        return Palette(names, names, names)
    return Palette()


def draw_surroundings(rng: np.random.Generator, palette: Palette = Palette()) -> tuple[str, str]:
    """The (ground, backdrop) textures of a scene: the first two draws of its generator."""
    return (palette.grounds[rng.integers(len(palette.grounds))],
            palette.backdrops[rng.integers(len(palette.backdrops))])


def build_scene(seed: int, cfg: SyntheticConfig, style: str) -> tuple[GaussianModel, str]:
    """The ground-truth Gaussians of scene ``seed`` and its caption."""
    rng = np.random.default_rng(seed)
    spacing = 1.0 / math.sqrt(cfg.gaussians_per_unit_area)
    palette = scene_palette(seed, cfg)
    ground_name, backdrop_name = draw_surroundings(rng, palette)
    surfaces = [ground_disc(3.2, spacing * 1.6, load_texture(ground_name, rng), rng)]
    if style == "orbit":
        surfaces.append(cylinder_wall(3.2, 2.2, spacing * 1.8, load_texture(backdrop_name, rng)))
    else:
        surfaces.append(backdrop_plane(2.2, 3.2, 2.6, spacing * 1.6, load_texture(backdrop_name, rng)))
    described = []
    placed: list[tuple[np.ndarray, float]] = []
    while len(placed) < cfg.num_objects:
        size = float(rng.uniform(0.35, 0.7))
        spread = 1.3 if style == "orbit" else 1.1
        xy = rng.uniform(-spread, spread, 2)
        if any(np.linalg.norm(xy - p[:2]) < 0.55 * (size + s) + 0.1 for p, s in placed):
            continue
        texture_name = palette.objects[rng.integers(len(palette.objects))]
        texture = load_texture(texture_name, rng)
        if rng.random() < 0.5:
            surfaces.append(box(np.array([xy[0], xy[1], 0.0]), size, spacing, texture))
            described.append(f"a {texture_name} box")
        else:
            center = np.array([xy[0], xy[1], size / 2])
            surfaces.append(sphere(center, size / 2, spacing, texture))
            described.append(f"a {texture_name} ball")
        placed.append((np.array([xy[0], xy[1], 0.0]), size))
    backdrop = "a wall" if style == "orbit" else "a backdrop"
    caption = (f"{', '.join(described[:-1])} and {described[-1]} on {ground_name} "
               f"in front of {backdrop} showing {backdrop_name.replace('_', ' ')}")
    return gaussians_from_surfaces(surfaces), caption


def camera_path(cfg: SyntheticConfig, style: str, seed: int) -> list[Camera]:
    """The capture path: an open orbit arc around the objects, or a forward-facing sweep."""
    rng = np.random.default_rng(seed + 7919)
    n = cfg.num_views
    cameras = []
    up = torch.tensor([0.0, 0.0, 1.0])
    start = float(rng.uniform(0, 2 * math.pi))
    for i in range(n):
        s = i / (n - 1)
        if style == "orbit":
            angle = start + math.radians(cfg.orbit_arc_deg) * s
            eye = [2.3 * math.cos(angle), 2.3 * math.sin(angle), 1.1 + 0.25 * math.sin(2 * math.pi * s)]
            target = [0.0, 0.0, 0.3]
        elif style == "forward":
            eye = [-1.4 + 2.8 * s, -2.6 + 0.2 * math.sin(2 * math.pi * s), 1.0 + 0.3 * math.cos(2 * math.pi * s)]
            target = [0.25 * (2 * s - 1), 0.8, 0.4]
        else:
            raise ValueError(f"synthetic.path_styles entries must be 'orbit' or 'forward', got {style!r}")
        cameras.append(Camera.look_at(torch.tensor(eye), torch.tensor(target), up, fov_x_deg=cfg.fov_x_deg,
                                      width=cfg.width, height=cfg.height))
    return cameras


def render_images(model: GaussianModel, cameras: list[Camera], background: list[float]) -> list[torch.Tensor]:
    """Images [3,H,W] in [0,1] of ``model`` at ``cameras`` (no gradients)."""
    return [image for image, _ in render_with_depth(model, cameras, background)]


def render_with_depth(model: GaussianModel, cameras: list[Camera],
                      background: list[float]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(image [3,H,W] in [0,1], depth [H,W]) of ``model`` at each camera (no gradients)."""
    bg = torch.tensor(background, dtype=torch.float32)
    out = []
    with torch.no_grad():
        for camera in cameras:
            rendered = render(model, camera, background=bg, sh_degree=0)
            out.append((rendered.image.clamp(0, 1), rendered.depth[0]))
    return out


def ground_truth_model(scene: Scene) -> GaussianModel:
    """The scene's true Gaussians in the frame its cameras use (the loader's normalisation applied)."""
    path = scene.root / GT_PLY
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no ground-truth scene (only synthetic scenes have one)")
    model = load_ply(path)
    with torch.no_grad():
        model.means.copy_((model.means - scene.world_offset) / scene.world_scale)
        model.log_scales.sub_(math.log(scene.world_scale))
    return model


def scene_background(scene: Scene) -> list[float]:
    """Background colour the ground truth was rendered with (black when the scene does not say)."""
    info = scene.root / "scene.json"
    return json.loads(info.read_text()).get("background", [0.0, 0.0, 0.0]) if info.is_file() else [0.0, 0.0, 0.0]


def render_ground_truth(scene: Scene, cameras: list[Camera]) -> torch.Tensor:
    """Ground truth [F,3,H,W] in [0,1] of a synthetic scene at arbitrary poses (e.g. trajectory frames)."""
    return torch.stack(render_images(ground_truth_model(scene), cameras, scene_background(scene)))


def observations(cameras: list[Camera], depths: list[torch.Tensor],
                 points: torch.Tensor) -> list[list[tuple[int, np.ndarray]]]:
    """COLMAP-style tracks: image index and pixel of every camera where each point is visible.

    A point counts as visible when it projects inside the image in front of the camera and its depth
    agrees with the rendered ground-truth depth there (not hidden behind another surface).
    """
    tracks: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(len(points))]
    for index, (camera, depth) in enumerate(zip(cameras, depths)):
        cam = points @ camera.rotation.T + camera.translation
        z = cam[:, 2]
        uv = (cam @ camera.K.T)[:, :2] / z.clamp_min(1e-6)[:, None]
        col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = (z > 1e-3) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
        surface = torch.zeros_like(z)
        surface[inside] = depth[row[inside], col[inside]]
        visible = inside & ((surface - z).abs() < 0.05 * z + 0.03)
        for p in torch.nonzero(visible).flatten().tolist():
            tracks[p].append((index, uv[p].numpy().astype(np.float64)))
    return tracks


def generate_scene(seed: int, cfg: SyntheticConfig, root: Path, force: bool = False) -> Path:
    """Write scene ``seed`` under ``root`` (images/, sparse/0, caption.txt, gt_scene.ply, scene.json).

    The scene is assembled in a temporary sibling directory and renamed into place, so a complete
    directory means a finished scene; existing scenes are kept unless ``force``.
    """
    target = Path(root) / scene_name(seed)
    textures = cfg.pretrain_textures if scene_palette(seed, cfg) != Palette() else None
    if (target / "scene.json").is_file() and not force:
        if json.loads((target / "scene.json").read_text()).get("textures") == textures:
            return target  # else the seed's folder holds the scene of another palette: made anew, never reused

    style = cfg.path_styles[seed % len(cfg.path_styles)]
    model, caption = build_scene(seed, cfg, style)
    cameras = camera_path(cfg, style, seed)
    rendered = render_with_depth(model, cameras, cfg.background)
    images = [image for image, _ in rendered]
    # SfM-like points: Gaussian centres that at least two images observe (what COLMAP could triangulate),
    # subsampled; their tracks let each view set initialise from the points its own views see.
    all_tracks = observations(cameras, [depth for _, depth in rendered], model.means.detach())
    candidates = torch.tensor([p for p, track in enumerate(all_tracks) if len(track) >= 2], dtype=torch.long)
    order = torch.randperm(len(candidates), generator=torch.Generator().manual_seed(seed))
    chosen = candidates[order[: cfg.init_points]].sort().values
    points = model.means.detach()[chosen]
    colors = (model.sh_dc.detach()[chosen, 0] * SH_C0 + 0.5).clamp(0, 1)
    tracks = [all_tracks[p] for p in chosen.tolist()]
    with atomic_directory(target) as tmp:
        names = [f"frame_{i:05d}.png" for i in range(len(cameras))]
        (tmp / "images").mkdir()
        for name, image in zip(names, images):
            array = (image.permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
            Image.fromarray(array).save(tmp / "images" / name)
        write_colmap_model(tmp / "sparse" / "0", cameras, names, points.numpy(), colors.numpy(), tracks)
        save_ply(model, tmp / GT_PLY)
        (tmp / "caption.txt").write_text(caption + "\n")
        record = {"seed": seed, "style": style, "num_gaussians": len(model), "background": list(cfg.background)}
        (tmp / "scene.json").write_text(json.dumps(record | ({"textures": textures} if textures else {})))
    return target


def generate_benchmark(cfg: SyntheticConfig, splits: tuple[str, ...] = ("train", "test"), force: bool = False,
                       progress: bool = True, pool: Executor | None = None) -> list[Path]:
    """Write the scenes of ``splits`` (deterministic by seed) under ``cfg.root``, in ``pool``'s processes
    when given."""
    overlap = overlapping_seeds(cfg)
    if overlap:
        raise ValueError(f"synthetic.train_seeds, val_seeds, test_seeds and pretrain_seeds overlap: {overlap}")
    seeds = [seed for split in splits for seed in split_seeds(cfg, split)]
    root = Path(cfg.root)
    if root.is_dir():  # half-assembled scenes of a killed run (generate_scene builds in ".<name>.*")
        for stale in root.glob(".scene_*"):
            shutil.rmtree(stale, ignore_errors=True)
    paths = []
    with Progress(disable=not progress) as bar:
        task = bar.add_task("synthetic scenes", total=len(seeds))
        for path in run_units(pool, generate_scene, [(seed, cfg, root, force) for seed in seeds]):
            paths.append(path)
            bar.advance(task)
    return paths
