"""The synthetic benchmark written in the on-disk layouts of the paper's datasets.

Each layout keeps what its loader reads and drops what real captures lack (no ground-truth Gaussians, no
captions): images in the preset's downscaled folder and a COLMAP model at full resolution, so the loader
rescales the intrinsics as it does for the real downloads. DL3DV comes with train / benchmark scene lists,
Mip-NeRF 360 optionally with ReconFusion's split files, NeRFBusters with its two captures.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from tracegs.data.config import SyntheticConfig
from tracegs.data.splits import every_nth_test, grow_evenly
from tracegs.data.synthetic import generate_benchmark

DOWNSCALE = {"dl3dv": 4, "mipnerf360": 4, "nerfbusters": 2}  # images_4 / images_2 next to sparse/0


def copy_scene(source: Path, target: Path, downscale: int, rename=lambda name: name) -> None:
    """``source`` (images/ + sparse/0 at image size) as ``images_{downscale}/`` + a full-resolution model."""
    import pycolmap  # after PIL and torch (bundled zlib, see tracegs/data/colmap.py)

    images = target / f"images_{downscale}"
    images.mkdir(parents=True)
    model = pycolmap.Reconstruction(str(source / "sparse" / "0"))
    for camera in model.cameras.values():
        camera.rescale(float(downscale))
    for image in model.images.values():
        shutil.copy(source / "images" / image.name, images / rename(image.name))
        image.name = rename(image.name)
    (target / "sparse" / "0").mkdir(parents=True)
    model.write(str(target / "sparse" / "0"))


def synthetic_scenes(root: Path, train_seeds: list[int], test_seeds: list[int], height: int, width: int,
                     num_views: int) -> tuple[list[Path], list[Path]]:
    cfg = SyntheticConfig(root=str(root / "synthetic"), train_seeds=train_seeds, test_seeds=test_seeds,
                          num_views=num_views, height=height, width=width, init_points=300)
    paths = generate_benchmark(cfg, progress=False)
    return paths[: len(train_seeds)], paths[len(train_seeds):]


def write_dl3dv(root: Path, train: list[Path], benchmark: list[Path]) -> Path:
    """``DL3DV-10K/<scene>/`` plus ``train_scenes.txt`` and ``benchmark_scenes.txt`` (one name a line)."""
    out = root / "DL3DV-10K"
    for scene in train + benchmark:
        copy_scene(scene, out / scene.name, DOWNSCALE["dl3dv"])
    (out / "train_scenes.txt").write_text("".join(f"{s.name}\n" for s in train))
    (out / "benchmark_scenes.txt").write_text("".join(f"{s.name}\n" for s in benchmark))
    return out


def write_mipnerf360(root: Path, scenes: list[Path], split_files: bool, view_counts=(3, 6, 9)) -> Path:
    """``mipnerf360/<scene>/`` and, with ``split_files``, ReconFusion's ``train_test_split_{n}.json``."""
    out = root / "mipnerf360"
    for scene in scenes:
        copy_scene(scene, out / scene.name, DOWNSCALE["mipnerf360"])
        if split_files:
            count = len(list((scene / "images").iterdir()))
            test = every_nth_test(count, 8)
            # Nested sets that skip the capture's first two training views, so they differ from the fallback rule.
            candidates = [i for i in range(count) if i not in test][2:]
            chosen: list[int] = []
            for n in view_counts:
                chosen = grow_evenly(candidates, chosen, n)
                (out / scene.name / f"train_test_split_{n}.json").write_text(
                    json.dumps({"train_ids": chosen, "test_ids": test}))
    return out


def write_nerfbusters(root: Path, scenes: list[Path], test_every: int = 8) -> Path:
    """``nerfbusters/<scene>/``: every ``test_every``-th frame belongs to the second (evaluation) capture."""
    out = root / "nerfbusters"
    for scene in scenes:
        names = sorted(p.name for p in (scene / "images").iterdir())
        capture = {n: 2 if i % test_every == 0 else 1 for i, n in enumerate(names)}
        copy_scene(scene, out / scene.name, DOWNSCALE["nerfbusters"],
                   lambda n, capture=capture: f"frame_{capture[n]}_{n}")
    return out
