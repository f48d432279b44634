"""Run GSFixer's own functions (GVCLab/GSFixer at 19e0216, ``Reconstruction/``) beside ours on the same inputs, and
write their outputs as the goldens the default suite compares ours against (``tests/goldens/gsfixer_release.json``).

Usage::

    git -C <GSFixer clone> archive 19e0216 Reconstruction | tar -x -C /tmp/gsfixer-release
    TRACEGS_GSFIXER_RELEASE=/tmp/gsfixer-release/Reconstruction .venv/bin/python benchmarks/gsfixer_crosscheck.py

Nothing of GSFixer is copied into the project: its modules are loaded from the path in ``TRACEGS_GSFIXER_RELEASE``,
their CUDA-only and unused top-level imports (the rasterizer, camera classes, pycolmap, OpenCV, torchvision)
stood in by empty modules while they load. What is run, each with fixed inputs and seeds:

- ``similarity_from_cameras``, ``transform_cameras`` (datasets/normalize.py) and ``generate_ellipse_path``
  (gsfixer/extrapolation/outpaint/sample_utils.py) as ``sparse.py`` l. 191-208 calls them, rounds 0-2, with the
  z phase drawn by ``np.random.random()`` after ``np.random.seed``;
- ``generate_overlapping_indices`` (gsfixer/extrapolation/outpaint/base.py l. 13-34): the windows;
- ``Dataset.__init__``'s sparse-view rule (datasets/colmap_debug.py l. 416-431) on a stand-in parser;
- ``ssim`` (utils/loss_utils.py l. 65-105), as ``metrics.py`` l. 25-35 and 74 feed it 8-bit PNGs.

The script then checks ours against what it wrote (``tests/config/test_gsfixer_goldens.py`` does the same from the file)
and exits 1 on a mismatch.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import json
import math
import os
import sys
import types
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

ENV = "TRACEGS_GSFIXER_RELEASE"
GOLDENS = Path(__file__).resolve().parents[1] / "tests" / "goldens" / "gsfixer_release.json"
COMMAND = (f"git -C <GSFixer clone> archive 19e0216 Reconstruction | tar -x -C /tmp/gsfixer-release && "
           f"{ENV}=/tmp/gsfixer-release/Reconstruction .venv/bin/python benchmarks/gsfixer_crosscheck.py")
ROUNDS = (0, 1, 2)
ELLIPSE_POSES = 85  # sparse.py l. 203
STUBBED = ("gaussian_renderer", "utils", "utils.camera_utils", "utils.graphics_utils", "pycolmap", "cv2",
           "torchvision", "datasets")


def release_root() -> Path | None:
    """The GSFixer ``Reconstruction/`` folder named by ``TRACEGS_GSFIXER_RELEASE``, or None when unset."""
    value = os.environ.get(ENV)
    if not value:
        return None
    root = Path(value)
    if not (root / "gsfixer" / "extrapolation" / "outpaint" / "sample_utils.py").is_file():
        raise SystemExit(f"{ENV}={value}: not GSFixer's Reconstruction/ folder (no gsfixer/extrapolation/outpaint/"
                         "sample_utils.py)")
    return root


@contextlib.contextmanager
def _stand_ins(root: Path) -> Iterator[None]:
    """Empty modules for GSFixer's top-level imports this check does not run, and a ``datasets`` package that
    does not execute its ``__init__`` (which builds the CUDA rasterizer); ``sys.modules`` restored after."""
    saved = {name: sys.modules.get(name) for name in STUBBED + ("datasets.normalize", "datasets.colmap_debug")}
    stubs = {name: types.ModuleType(name) for name in STUBBED}
    stubs["gaussian_renderer"].render = None
    stubs["utils.camera_utils"].Camera = stubs["utils.camera_utils"].SampleCamera = None
    stubs["utils.camera_utils"].CameraInfo = None
    stubs["utils.graphics_utils"].focal2fov = None
    stubs["pycolmap"].SceneManager = None
    stubs["datasets"].__path__ = [str(root / "datasets")]
    sys.modules.update(stubs)
    try:
        yield
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def _load(root: Path, relative: str, name: str) -> types.ModuleType:
    spec = importlib.util.spec_from_file_location(name, root / relative)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def release_functions(root: Path) -> SimpleNamespace:
    """GSFixer's functions this check runs, loaded from ``root``."""
    with _stand_ins(root):
        normalize = importlib.import_module("datasets.normalize")
        colmap = importlib.import_module("datasets.colmap_debug")
        sample_utils = _load(root, "gsfixer/extrapolation/outpaint/sample_utils.py", "_gsfixer_sample_utils")
        base = _load(root, "gsfixer/extrapolation/outpaint/base.py", "_gsfixer_outpaint_base")
        loss_utils = _load(root, "utils/loss_utils.py", "_gsfixer_loss_utils")
    return SimpleNamespace(similarity_from_cameras=normalize.similarity_from_cameras,
                           transform_cameras=normalize.transform_cameras,
                           generate_ellipse_path=sample_utils.generate_ellipse_path,
                           outpaint_base=base.OutpaintBase, dataset=colmap.Dataset, ssim=loss_utils.ssim)


def camera_sets() -> dict[str, np.ndarray]:
    """Camera-to-world poses [N,4,4] (OpenCV axes) of two captures in a world whose up is not an axis: three views
    of an object and twelve round it at uneven heights and distances, each looking near a common point."""
    rng = np.random.default_rng(7)
    tilt = _rotation(np.array([0.3, -0.5, 0.2]))  # the capture's world is turned, so GSFixer's normalisation acts
    sets = {}
    for name, count, spread in (("three", 3, 0.9), ("twelve", 12, 2 * math.pi)):
        poses = []
        for angle in np.linspace(0.0, spread, count, endpoint=spread < 2 * math.pi):
            eye = np.array([(3.0 + rng.uniform(-0.5, 0.5)) * math.cos(angle),
                            (2.0 + rng.uniform(-0.5, 0.5)) * math.sin(angle), rng.uniform(0.2, 1.2)])
            target = np.array([0.4, -0.2, 0.1]) + rng.normal(0.0, 0.1, 3)
            forward = (target - eye) / np.linalg.norm(target - eye)
            right = np.cross(forward, [0.0, 0.0, 1.0])
            right /= np.linalg.norm(right)
            pose = np.eye(4)
            pose[:3, :3] = tilt @ np.stack([right, np.cross(forward, right), forward], axis=1)
            pose[:3, 3] = tilt @ eye + np.array([1.5, -0.7, 0.4])
            poses.append(pose)
        sets[name] = np.stack(poses)
    return sets


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(axis_angle)
    k = axis_angle / angle
    skew = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * skew + (1 - math.cos(angle)) * skew @ skew


def ellipse_goldens(release: SimpleNamespace) -> dict:
    """Per camera set and round: GSFixer's world, its ellipse there and mapped back, as ``sparse.py`` l. 191-208
    draws and calls it (seed 100 + round before the round)."""
    out = {}
    for name, poses in camera_sets().items():
        world = release.similarity_from_cameras(poses)
        normalised = release.transform_cameras(world, poses)
        rounds = []
        for i in ROUNDS:
            np.random.seed(100 + i)
            z_phase = float(np.random.random())  # sparse.py l. 199
            z_variation = max(1.5 - 0.2 * i, 0.5)  # l. 198-201
            path = release.generate_ellipse_path(normalised[:, :3], ELLIPSE_POSES, z_variation=z_variation,
                                                 z_phase=z_phase, scale=i)
            padded = np.concatenate([path, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (len(path), 1, 1))], axis=1)
            back = release.transform_cameras(np.linalg.inv(world), padded)
            rounds.append({"round": i, "z_variation": z_variation, "z_phase": z_phase, "pitch_degrees": 2.0 * i,
                           "path": path.tolist(), "in_our_world": back[:, :3].tolist()})
        out[name] = {"camera_to_worlds": poses[:, :3].tolist(), "world": world.tolist(), "rounds": rounds}
    return out


WINDOW_CASES = ((85, 49), (85, 13), (20, 13), (100, 49), (64, 25))


def window_goldens(release: SimpleNamespace) -> list[dict]:
    """``generate_overlapping_indices(total)`` with ``args.num_frames`` (windows of num_frames // 3 + 1 poses)."""
    out = []
    for total, frames in WINDOW_CASES:
        starts, overlaps = release.outpaint_base(None, None, SimpleNamespace(num_frames=frames)) \
            .generate_overlapping_indices(total)
        out.append({"total": total, "num_frames": frames, "starts": [int(s) for s in starts],
                    "overlaps": [int(o) for o in overlaps]})
    return out


SPARSE_CASES = ((24, 3), (50, 3), (50, 6), (97, 9), (185, 3), (185, 6), (185, 9), (311, 24))


def sparse_view_goldens(release: SimpleNamespace) -> list[dict]:
    """The train (sparse) and test indices ``Dataset`` picks for a scene of ``images`` images without a split file
    (test_every 8), on a stand-in parser; image loading is skipped."""
    probe = type("SplitOnly", (release.dataset,), {"load_image_into_memory": lambda self: None})
    out = []
    for images, views in SPARSE_CASES:
        parser = SimpleNamespace(image_names=[f"{i:04d}" for i in range(images)], data_dir="/nonexistent",
                                 filter_points_sparse=lambda indices: None)
        args = SimpleNamespace(outpaint_type="sparse", dataset=SimpleNamespace(test_every=8))
        train = probe(args, parser, split="train", sparse_view=views).indices
        test = probe(args, parser, split="test", sparse_view=views).indices
        out.append({"images": images, "views": views, "train": [int(i) for i in train],
                    "test": [int(i) for i in test]})
    return out


def ssim_goldens(release: SimpleNamespace) -> list[dict]:
    """GSFixer's ``ssim`` of 8-bit image pairs as ``metrics.py`` reads them (``to_tensor``: uint8 / 255, [1,3,H,W]):
    a noisy pair, a smooth pair and a pair differing by a shift."""
    rng = np.random.default_rng(11)
    ys, xs = np.mgrid[0:18, 0:24]
    smooth = np.stack([np.sin(xs / 4.0 + c) * np.cos(ys / 5.0) for c in range(3)]) * 100 + 128
    pairs = [(rng.integers(0, 256, (3, 18, 24)), rng.integers(0, 256, (3, 18, 24))),
             (smooth, smooth + rng.normal(0, 6, smooth.shape)),
             (smooth, np.roll(smooth, 2, axis=2))]
    out = []
    for a, b in pairs:
        a, b = (np.clip(np.rint(x), 0, 255).astype(np.uint8) for x in (a, b))
        value = release.ssim(torch.from_numpy(a)[None].float() / 255, torch.from_numpy(b)[None].float() / 255)
        out.append({"a": a.tolist(), "b": b.tolist(), "ssim": float(value)})
    return out


def make_goldens(root: Path) -> dict:
    release = release_functions(root)
    with contextlib.redirect_stdout(io.StringIO()):  # GSFixer prints its indices as it picks them
        return {"command": COMMAND, "release": "GVCLab/GSFixer 19e0216, Reconstruction/",
                "ellipse": ellipse_goldens(release), "windows": window_goldens(release),
                "sparse_views": sparse_view_goldens(release), "ssim": ssim_goldens(release)}


def compare(goldens: dict) -> list[str]:
    """What of ours differs from ``goldens``: one line per mismatch, empty when all agree (poses, worlds and SSIM
    within 1e-6, indices exactly)."""
    from tracegs.data.splits import make_split
    from tracegs.eval.metrics import gsfixer_ssim
    from tracegs.splat.trajectory import gsfixer_ellipse_path, gsfixer_world, transform_cameras, window_starts

    failures = []

    def close(label: str, ours: torch.Tensor, theirs, tolerance: float = 1e-6) -> None:
        error = (ours.double() - torch.tensor(theirs, dtype=torch.float64)).abs().max().item()
        if not error <= tolerance:
            failures.append(f"{label}: max difference {error:.3g} > {tolerance:g}")

    for name, case in goldens["ellipse"].items():
        poses = torch.tensor(case["camera_to_worlds"], dtype=torch.float64)
        world = gsfixer_world(poses)
        close(f"ellipse/{name}/world", world, case["world"])
        for entry in case["rounds"]:
            label = f"ellipse/{name}/round {entry['round']}"
            path = gsfixer_ellipse_path(transform_cameras(world, poses), ELLIPSE_POSES, entry["z_variation"],
                                        entry["z_phase"], entry["pitch_degrees"])
            close(f"{label}/path", path, entry["path"])
            close(f"{label}/in our world", transform_cameras(torch.linalg.inv(world), path), entry["in_our_world"])
    for case in goldens["windows"]:
        ours = window_starts(case["total"], case["num_frames"] // 3 + 1)
        if ours != case["starts"]:
            failures.append(f"windows {case['total']}/{case['num_frames']}: ours {ours}, GSFixer's {case['starts']}")
    for case in goldens["sparse_views"]:
        split = make_split(case["images"], [case["views"]], 8, view_rule="linspace")
        ours = (split.views(case["views"]), split.test)
        if ours != (case["train"], case["test"]):
            failures.append(f"sparse views {case['images']}/{case['views']}: ours {ours}, GSFixer's "
                            f"{(case['train'], case['test'])}")
    for k, case in enumerate(goldens["ssim"]):
        ours = gsfixer_ssim(torch.tensor(case["a"], dtype=torch.uint8), torch.tensor(case["b"], dtype=torch.uint8))
        close(f"ssim/{k}", ours, case["ssim"])
    return failures


def main() -> int:
    root = release_root()
    if root is None:
        print(f"set {ENV} to GSFixer's Reconstruction/ folder: {COMMAND}", file=sys.stderr)
        return 2
    goldens = make_goldens(root)
    GOLDENS.parent.mkdir(parents=True, exist_ok=True)
    GOLDENS.write_text(json.dumps(goldens, separators=(",", ":")) + "\n")
    failures = compare(goldens)
    print("\n".join(failures) if failures else f"ours agree with GSFixer's release; goldens written to {GOLDENS}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
