"""Structure-from-motion for a capture without a COLMAP model: photos or a video in, a scene folder out.

pycolmap runs COLMAP's pipeline (Schönberger and Frahm, "Structure-from-Motion Revisited", CVPR 2016): SIFT
features, exhaustive or sequential matching with geometric verification, incremental mapping, then undistortion
to a PINHOLE camera, the only model the loader reads (tracegs.data.colmap). The scene folder it writes
(``images/`` + ``sparse/0``, COLMAP's image_undistorter layout, and ``sfm.json``, what the reconstruction found)
is a product like any other: keyed by the names and bytes of the photos (a video: its bytes and the frame count)
and the settings that shape it, assembled in a temporary folder and renamed into place, reused by a rerun (and
copied for the same photos in a folder of another name). Its images are undistorted at ``scene_size`` on the long
side, the most a fit of it can use.

The photos are checked before they are trusted (:func:`working_photos`): each is decoded whole, turned upright by
its EXIF orientation and, when longer than the size SfM works at, downsized once. Photos of several sizes get a
camera each, and the model they give is checked against each pair's own two-view geometry
(:func:`_require_consistent`).

A video is reduced to photos first: ``frames`` equal windows of it, the sharpest frame of each by the variance of
its Laplacian (Pech-Pacheco et al., "Diatom autofocusing in brightfield microscopy", ICPR 2000), so motion-blurred
frames are passed over.

pycolmap bundles its own zlib; it is imported inside the functions that need it, after PIL and torch are loaded
(as in tracegs.data.colmap).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import math
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps

from tracegs.content import (
    DIGEST_CHARS,
    PHOTO_SUFFIXES,
    capture_digest,
    capture_files,
    names_and_bytes_digest,
    photo_folder,
)
from tracegs.data.config import Matcher, SfmConfig
from tracegs.data.splits import images_needed
from tracegs.errors import ConfigError, InputFileError, one_line
from tracegs.io import atomic_directory, write_json_atomic
from tracegs.processes import import_keeping_sigterm

log = logging.getLogger(__name__)

# Deployment fits 3DGS from at least two views and scores it on at least one held out.
MIN_IMAGES = 3
RECORD = "sfm.json"
# Settings that change where or how fast a reconstruction is made, not what it is.
EXECUTION_FIELDS = ("dir", "threads")
NAMES_SHOWN = 5
EXIF_ORIENTATION = 0x0112  # the EXIF tag saying how a camera was held
PROGRESS_EVERY = 10  # registered images between two progress lines of the mapper
# A reconstruction from photos of several sizes (tracegs.data.sfm._require_consistent). A camera whose points
# reproject worse than this is fitted wrongly (COLMAP's mapper filters observations at 4 px).
MAX_CAMERA_REPROJECTION_PX = 2.0
# A view whose rotation, relative to the views it was matched with, differs from each pair's own two-view
# estimate by more than this (median over its strongest pairs) is misplaced. A pair's estimate uses the guessed
# focal length of photos without EXIF, which biases it by a few degrees; a camera with a wrong focal length puts its
# views tens of degrees off (views about 55 degrees off were seen with photos of two sizes).
MAX_ROTATION_DISAGREEMENT_DEG = 10.0
# The pairs a view is judged by: its this many pairs with the most inlier matches. A weak pair's own estimate is
# often wrong: photos 50-100 degrees apart with 15-60 inliers gave two-view rotations of about 1 degree, 50-130
# degrees off a model whose every camera was within 1.1 degrees of the truth, and outvoted the view's good pairs.
STRONGEST_PAIRS = 3


def _names(paths: list[str]) -> str:
    shown = ", ".join(paths[:NAMES_SHOWN])
    return shown + (f" and {len(paths) - NAMES_SHOWN} more" if len(paths) > NAMES_SHOWN else "")


@contextlib.contextmanager
def _quiet_colmap(least: str = "ERROR") -> Iterator[None]:
    """COLMAP's own log (glog) off stderr and out of /tmp while it runs: a refused command prints one line, and
    what the reconstruction found goes to this module's log instead. Its messages from ``least`` up still reach
    stderr: errors, unless a caller reports that outcome itself."""
    pycolmap = import_keeping_sigterm("pycolmap")

    flags = pycolmap.logging
    before = flags.logtostderr, flags.minloglevel
    flags.logtostderr, flags.minloglevel = True, int(getattr(flags, least))
    try:
        yield
    finally:
        flags.logtostderr, flags.minloglevel = before


def _product_key(inputs: str, cfg: SfmConfig, **more: object) -> str:
    """The digest naming a reconstruction's folder: of its inputs' content and the settings that shape it."""
    settings = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in EXECUTION_FIELDS}
    payload = json.dumps({"inputs": inputs, **settings, **more}, sort_keys=True, default=str)
    return hashlib.sha256(payload.encode()).hexdigest()[:DIGEST_CHARS]


def reconstruct_photos(capture: Path, cfg: SfmConfig, views: int, test_every: int) -> Path:
    """The scene folder structure-from-motion makes of the photos in ``capture`` (or its ``images/``): made
    once under ``cfg.dir`` and reused. Files that are not photos are ignored, with a log line; a capture too
    small for ``views`` training views and the held-out ones (every ``test_every``-th) is refused."""
    folder = photo_folder(capture)
    photos, others = capture_files(capture)
    if others:
        log.info("%s: ignored %d file(s) that are not photos (%s); photos end in %s", folder, len(others),
                 _names([p.name for p in others]), " ".join(PHOTO_SUFFIXES))
    names = [p.name for p in photos]
    _require_images(folder, names, "photos", views, test_every)
    # Keyed by the photos' names and bytes, not the folder's name; the scene inside is named by the folder.
    target = Path(cfg.dir) / _product_key(capture_digest(capture), cfg) / capture.name
    if not _reused(target, views, test_every):
        with atomic_directory(target) as staging:
            if _copied_twin(target, staging):
                _require_registered(json.loads((staging / RECORD).read_text()), capture, views, test_every)
            else:
                _reconstruct(staging, folder, names, cfg, views, test_every, capture, sequential=False)
    return target


def _copied_twin(target: Path, staging: Path) -> bool:
    """Whether a finished reconstruction of the same photos under another folder name was copied into ``staging``.
    A renamed capture then gets the very same cameras and points: COLMAP's multithreaded mapping and bundle
    adjustment do not repeat to the bit, and a restore's numbers would follow the name instead of the photos."""
    twins = sorted(p for p in target.parent.iterdir()  # finished folders only, not another run's staging
                   if p != target and not p.name.startswith(".") and (p / RECORD).is_file())
    if not twins:
        return False
    shutil.copytree(twins[0], staging, dirs_exist_ok=True)
    log.info("%s: the same photos were reconstructed as %s: copied from %s", target.name, twins[0].name, twins[0])
    return True


def reconstruct_video(video: Path, frames: int, cfg: SfmConfig, views: int, test_every: int) -> Path:
    """The scene folder of ``frames`` frames sampled from ``video`` (:func:`sample_frames`, kept beside it in
    ``frames/``), reconstructed as photos matched in sequence; made once under ``cfg.dir`` and reused."""
    if frames < MIN_IMAGES:
        raise ConfigError("capture.frames", f"{frames}: structure-from-motion needs at least {MIN_IMAGES} frames")
    if not video.is_file():
        raise InputFileError(video, "no such file" if not video.exists() else "is not a file",
                             "give capture.video a video file")
    key = _product_key(names_and_bytes_digest(video), cfg, frames=frames, name=video.stem)
    target = Path(cfg.dir) / key / video.stem
    if not _reused(target, views, test_every):
        with atomic_directory(target.parent) as staging:
            sampled = sample_frames(video, frames, staging / "frames")
            names = [p.name for p in sampled]
            _require_images(video, names, "frames", views, test_every)
            _reconstruct(staging / target.name, staging / "frames", names, cfg, views, test_every, video,
                         sequential=True)
    return target


def _require_images(where: Path, names: list[str], kind: str, views: int, test_every: int) -> None:
    """Refuse, before any matching, a capture with fewer than :data:`MIN_IMAGES` images or too few for ``views``."""
    if len(names) < MIN_IMAGES:
        raise InputFileError(where, f"{len(names)} {kind}{f' ({_names(names)})' if names else ''}; "
                                    f"structure-from-motion needs at least {MIN_IMAGES}",
                             f"add photos of the scene (ending in {' '.join(PHOTO_SUFFIXES)})" if kind == "photos"
                             else "give a longer video")
    needed = images_needed(views, test_every)
    if len(names) < needed:
        raise ConfigError("capture.views", f"{views}: {where} gives {len(names)} {kind}, and {views} training views "
                                           f"plus the held-out ones (every {test_every}th image) need {needed}; "
                                           "ask for fewer views or capture more")


def _reused(target: Path, views: int, test_every: int) -> bool:
    """Whether a finished reconstruction is at ``target`` (refused when it registered too few images for
    ``views``)."""
    if not (target / RECORD).is_file():
        return False
    record = json.loads((target / RECORD).read_text())
    log.info("%s: reusing the reconstruction at %s (%d of %d images registered, mean reprojection error "
             "%.2f px)", target.name, target, len(record["registered"]), record["images"],
             record["mean_reprojection_error"])
    _require_registered(record, target, views, test_every)
    return True


def _reconstruct(scene: Path, images: Path, names: list[str], cfg: SfmConfig, views: int, test_every: int,
                 capture: Path, sequential: bool) -> None:
    """Run SfM on ``names`` in ``images`` and write the undistorted scene folder ``scene``; refuse, before
    anything is kept, a reconstruction that registers too few images of ``capture`` for ``views``."""
    # lazily, after PIL and torch (bundled zlib, see module docstring)
    pycolmap = import_keeping_sigterm("pycolmap")

    if cfg.camera_model not in pycolmap.CameraModelId.__members__:
        raise ConfigError("capture.sfm.camera_model", f"{cfg.camera_model!r} is not a COLMAP camera model; "
                                                      "use SIMPLE_RADIAL, OPENCV, PINHOLE, ...")
    work = scene / ".work"  # inside the staging folder, so a refused reconstruction takes it along
    work.mkdir(parents=True)
    images = working_photos(images, names, work / "photos", cfg.max_image_size)
    database = work / "database.db"
    started = time.perf_counter()
    matcher = Matcher.parse(cfg.matcher, "capture.sfm.matcher")
    if matcher == Matcher.auto:
        matcher = Matcher.sequential if sequential else Matcher.exhaustive
    log.info("%s: structure-from-motion of %d images with pycolmap: SIFT features", scene.name, len(names))
    with _quiet_colmap():
        sizes = _extract(database, images, names, cfg)
        log.info("%s: %d images, %d camera(s) (one per image size: %s); %s matching", scene.name, len(names),
                 len(sizes), ", ".join(f"{w}x{h}" for w, h in sizes), matcher.value)
        # Photos of several sizes: each pair's own relative pose is kept, to check the model against it.
        _match(database, matcher, cfg, relative_poses=len(sizes) > 1)
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads, options.min_model_size, options.random_seed = cfg.threads, cfg.min_model_size, cfg.seed
        placed = 0

        def progress() -> None:  # called by the mapper after each image it registers
            nonlocal placed
            placed += 1
            if placed % PROGRESS_EVERY == 0:
                log.info("%s: mapping, %d images registered so far", scene.name, placed)

        # A mapping that makes no model says so as an error; the refusal below says it, and why, in one line.
        with _quiet_colmap("FATAL"):
            models = pycolmap.incremental_mapping(database, images, work / "models", options,
                                                  next_image_callback=progress)
        record = _findings(database, names, models, options)
        record["cameras"], record["seconds"] = [list(size) for size in sizes], round(time.perf_counter() - started, 2)
        _log_findings(scene.name, record)
        _require_registered(record, capture, views, test_every)
        largest = max(models.values(), key=lambda model: model.num_reg_images())
        if len(sizes) > 1:
            record["consistency"] = _require_consistent(largest, database, sizes, capture)
        (work / "model").mkdir()
        largest.write(work / "model")
        undistorted = work / "undistorted"
        undistortion = pycolmap.UndistortCameraOptions()
        undistortion.max_image_size = cfg.scene_size
        pycolmap.undistort_images(undistorted, work / "model", images, undistort_options=undistortion,
                                  num_threads=cfg.threads)
    (scene / "sparse").mkdir()
    (undistorted / "images").rename(scene / "images")
    (undistorted / "sparse").rename(scene / "sparse" / "0")
    shutil.rmtree(work)
    write_json_atomic(record, scene / RECORD)


def working_photos(images: Path, names: list[str], out: Path, longest: int) -> Path:
    """The folder of ``names`` as SfM reads them: ``images`` itself, or ``out`` with links to the photos kept as
    they are and a working copy of each other one.

    Every photo is decoded whole first: COLMAP reads what a truncated file holds and fills the rest with grey, and
    the undistorted copy it writes is a valid image, so no later check would see the damage; a photo that does not
    decode is refused, named. A photo with an EXIF orientation (a phone held upright) is turned upright, as the
    loader reads it (tracegs.data.images), since COLMAP reads the stored pixels and its undistorted images keep the
    tag. A photo longer than ``longest`` pixels on its long side is downsized to it once, here, with the JPEG
    decoder's own reduction (PIL's draft mode), so no full-size copy is held or written: SIFT, the mapper and
    the undistortion then all read the working size, which bounds memory by it rather than by the photos."""
    changed = []
    for name in names:
        try:
            with Image.open(images / name) as photo:
                turned = photo.getexif().get(EXIF_ORIENTATION, 1) != 1
                large = max(photo.size) > longest
                if large:  # a reduced decode: at least ``longest`` on the long side, a power of two smaller
                    scale = longest / max(photo.size)
                    photo.draft("RGB", (round(photo.size[0] * scale), round(photo.size[1] * scale)))
                photo.load()
                if turned or large:
                    _write_working_copy(photo, out / name, longest)
                    changed.append(name)
        except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:  # PIL's decode errors
            raise InputFileError(images / name, f"cannot decode the photo ({one_line(error)})",
                                 "replace it with an intact copy or remove it from the capture") from error
    if not changed:
        return images
    for name in names:
        if name not in changed:
            (out / name).symlink_to(images / name)
    log.info("%d photos turned upright by their EXIF orientation or downsized to %d px on the long side (%s)",
             len(changed), longest, _names(changed))
    return out


def _write_working_copy(photo: Image.Image, path: Path, longest: int) -> None:
    """``photo`` upright and at most ``longest`` pixels on its long side, in its own format, at ``path``."""
    upright = ImageOps.exif_transpose(photo)
    if max(upright.size) > longest:
        scale = longest / max(upright.size)
        upright = upright.resize((max(1, round(upright.size[0] * scale)), max(1, round(upright.size[1] * scale))),
                                 Image.Resampling.LANCZOS)
    path.parent.mkdir(exist_ok=True)
    # The EXIF kept (less the orientation, applied): COLMAP's prior focal length comes from the lens and sensor it
    # names, a fraction of the image width that the downsizing does not change.
    upright.save(path, format=photo.format, quality=95, exif=upright.getexif())


def _extract(database: Path, images: Path, names: list[str], cfg: SfmConfig) -> list[tuple[int, int]]:
    """SIFT features of ``names`` into ``database``, one camera per image size (COLMAP's AUTO mode gives
    one per image in pycolmap 4.2, so each size is read on its own in SINGLE mode); returns the sizes."""
    pycolmap = import_keeping_sigterm("pycolmap")

    by_size: dict[tuple[int, int], list[str]] = {}
    for name in names:
        with Image.open(images / name) as image:  # decoded whole already (working_photos)
            by_size.setdefault(image.size, []).append(name)  # as stored, as COLMAP reads it
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads, extraction.max_image_size = cfg.threads, cfg.max_image_size
    extraction.sift.max_num_features = cfg.max_features
    for group in by_size.values():
        pycolmap.extract_features(database, images, image_names=group, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction)
    return sorted(by_size)


def _match(database: Path, matcher: Matcher, cfg: SfmConfig, relative_poses: bool) -> None:
    """Match and verify pairs into ``database``; with ``relative_poses``, each verified pair's relative pose too
    (from its essential matrix), which :func:`_require_consistent` checks the model against."""
    pycolmap = import_keeping_sigterm("pycolmap")

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = cfg.threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = cfg.seed
    verification.compute_relative_pose = relative_poses
    if matcher == Matcher.sequential:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap, pairing.num_threads = cfg.sequential_overlap, cfg.threads
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification)
    else:
        pycolmap.match_exhaustive(database, matching_options=matching, verification_options=verification)


def _rotation_angle_deg(rotation: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def strongest_pair_medians(pairs: dict[str, list[tuple[int, float]]]) -> dict[str, float]:
    """Per view, the median rotation disagreement (degrees) over its :data:`STRONGEST_PAIRS` pairs with the most
    inlier matches; ``pairs[view]`` lists (inlier matches, disagreement) of each of its pairs."""
    return {name: float(np.median([angle for _, angle in sorted(found, key=lambda pair: -pair[0])[:STRONGEST_PAIRS]]))
            for name, found in pairs.items()}


def _require_consistent(model, database: Path, sizes: list[tuple[int, int]], capture: Path) -> dict:
    """Check a reconstruction of photos of several sizes (one camera each), and return what was measured.

    Cameras of different sizes share no intrinsics, so the mapper can settle on a wrong focal length for one of
    them and place its views wrongly while every reprojection error stays small. Two measures that such a model
    fails: each camera's mean reprojection error (at most :data:`MAX_CAMERA_REPROJECTION_PX`), and rotation
    consistency: the relative rotation the model gives each verified pair of registered views against the one
    the pair's own essential matrix gives (two-view geometry, independent of the mapper); a view whose median
    disagreement over its strongest pairs (``misplaced_views``) exceeds :data:`MAX_ROTATION_DISAGREEMENT_DEG` is
    misplaced. Either failure is refused in one line naming the sizes."""
    pycolmap = import_keeping_sigterm("pycolmap")

    # Pairs whose relative pose comes from an essential matrix (a homography's decomposition is ambiguous).
    epipolar = (pycolmap.TwoViewGeometryConfiguration.CALIBRATED, pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED)
    size_of = {camera_id: (camera.width, camera.height) for camera_id, camera in model.cameras.items()}
    errors: dict[tuple[int, int], list[float]] = {}
    for image in model.images.values():
        for point in image.points2D:
            if point.has_point3D():
                errors.setdefault(size_of[image.camera_id], []).append(model.points3D[point.point3D_id].error)
    per_camera = {f"{w}x{h}": float(np.mean(values)) for (w, h), values in sorted(errors.items())}
    placed = {image_id: image for image_id, image in model.images.items() if image.has_pose}
    with pycolmap.Database.open(database) as db:
        pairs, geometries = db.read_two_view_geometries()
    disagreement: dict[str, list[tuple[int, float]]] = {}
    for pair, geometry in zip(pairs, geometries):
        first, second = pycolmap.pair_id_to_image_pair(pair)
        if first not in placed or second not in placed or geometry.cam2_from_cam1 is None or (
                geometry.config not in epipolar):
            continue
        model_relative = (placed[second].cam_from_world().rotation.matrix()
                          @ placed[first].cam_from_world().rotation.matrix().T)
        angle = _rotation_angle_deg(geometry.cam2_from_cam1.rotation.matrix() @ model_relative.T)
        for image_id in (first, second):
            disagreement.setdefault(placed[image_id].name, []).append((len(geometry.inlier_matches), angle))
    medians = strongest_pair_medians(disagreement)
    misplaced = sorted(name for name, median in medians.items() if median > MAX_ROTATION_DISAGREEMENT_DEG)
    shown = ", ".join(f"{w}x{h}" for w, h in sizes)
    advice = "resize the photos to one size, or keep those of one size only"
    worst = max(per_camera.items(), key=lambda item: item[1])
    if worst[1] > MAX_CAMERA_REPROJECTION_PX:
        raise InputFileError(capture, f"photos of {len(sizes)} sizes ({shown}), one camera each, give a model whose "
                                      f"{worst[0]} camera reprojects with a mean error of {worst[1]:.2f} px (at most "
                                      f"{MAX_CAMERA_REPROJECTION_PX} px)", advice)
    if misplaced:
        raise InputFileError(capture, f"photos of {len(sizes)} sizes ({shown}), one camera each, give a model that "
                                      f"places {len(misplaced)} view(s) at rotations their photo pairs disagree with "
                                      f"by a median of {max(medians[name] for name in misplaced):.0f} deg at most "
                                      f"(over {MAX_ROTATION_DISAGREEMENT_DEG} deg): {_names(misplaced)}", advice)
    return {"reprojection_error_px": per_camera,
            "rotation_disagreement_deg": max(medians.values()) if medians else None}


def _findings(database: Path, names: list[str], models: dict, options) -> dict:
    """What the reconstruction found: the largest model's images, and why each other image is not in it.

    The reasons are what the database and the mapper's thresholds can prove, from the pairs the mapper loads (those
    with at least ``options.min_num_matches`` verified matches): an image with no such pair has no matches to any
    other; with no model at all, none could be started; an image with fewer verified matches with the registered
    images, all pairs together, than ``abs_pose_min_num_inliers`` could not be placed (placing one needs that many
    2D-3D correspondences, each from a match with a registered image, or twice that many 2D-2D ones), so its
    overlap was too little; any other was matched well enough yet not placed by the mapper. ``options`` are the
    mapping's pycolmap.IncrementalPipelineOptions. The record keeps, for each image left out though matched, its
    verified matches with the registered images (with no model: the most it has with any one image), so the
    refusal can say how far each was from being placed, a reused reconstruction's too."""
    pycolmap = import_keeping_sigterm("pycolmap")

    with pycolmap.Database.open(database) as db:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        pairs, inliers = db.read_two_view_geometry_num_inliers()
    verified = [(pycolmap.pair_id_to_image_pair(pair), count) for pair, count in zip(pairs, inliers)
                if count >= options.min_num_matches]
    ordered = sorted(models.values(), key=lambda model: -model.num_reg_images())
    groups = [sorted(image.name for image in model.images.values() if image.has_pose) for model in ordered]
    registered = groups[0] if groups else []
    # COLMAP lets a later model re-register images of an earlier one: only the others are left out.
    others = [kept for group in groups[1:] if (kept := [name for name in group if name not in registered])]
    elsewhere = {name for group in others for name in group}
    placed = {ids[name] for name in registered}
    most_with_one: dict[int, int] = {}  # an image's verified matches with any one other image, at most
    with_registered: dict[int, int] = {}  # an image's verified matches with the registered images, all together
    for (first, second), count in verified:
        for image, other in ((first, second), (second, first)):
            most_with_one[image] = max(most_with_one.get(image, 0), count)
            if other in placed:
                with_registered[image] = with_registered.get(image, 0) + count
    minimum = options.mapper.abs_pose_min_num_inliers
    left_out, matches = {}, {}
    for name in names:
        if name in registered:
            continue
        image = ids.get(name)
        if image is None or name in elsewhere or image not in most_with_one:
            left_out[name] = ("unreadable" if image is None else "another model" if name in elsewhere
                              else "no matches")
        elif not registered:
            left_out[name], matches[name] = "no start", most_with_one[image]
        else:
            count = with_registered.get(image, 0)
            left_out[name], matches[name] = ("too little overlap" if count < minimum else "not placed"), count
    largest = ordered[0] if ordered else None
    return {
        "images": len(names), "registered": registered, "left_out": left_out, "verified_matches": matches,
        "min_matches_to_place": minimum, "other_models": others,
        "mean_reprojection_error": largest.compute_mean_reprojection_error() if largest else None,
        "points": largest.num_points3D() if largest else 0,
    }


REASONS = {"no matches": "without matches to any other", "too little overlap": "with too little overlap to be placed",
           "not placed": "matched to the registered images but not placed by the mapper",
           "no start": "matched, but with no pair the mapper could start a model from",
           "unreadable": "that COLMAP could not read", "another model": "in separate models"}


def _why_left_out(record: dict) -> str:
    by_reason: dict[str, list[str]] = {}
    for name, reason in record["left_out"].items():
        by_reason.setdefault(reason, []).append(name)
    return "; ".join(f"{len(names)} {REASONS[reason]}{_matches(record, reason, names)}: {_names(names)}"
                     for reason, names in by_reason.items())


def _matches(record: dict, reason: str, names: list[str]) -> str:
    """How many verified matches the images left out for ``reason`` had at most, where the record holds it (a
    record written before it was kept does not)."""
    counts = record.get("verified_matches", {})
    if reason not in ("too little overlap", "not placed", "no start") or not all(name in counts for name in names):
        return ""
    most = max(counts[name] for name in names)
    if reason == "no start":
        return f", at most {most} verified matches with any other image"
    if reason == "not placed":
        return f", {min(counts[name] for name in names)} or more verified matches with the registered images each"
    return (f", at most {most} verified matches with the registered images where the mapper needs "
            f"{record['min_matches_to_place']}")


def _log_findings(name: str, record: dict) -> None:
    registered = len(record["registered"])
    log.info("%s: structure-from-motion registered %d of %d images, mean reprojection error %s, %d points (%.1f s)",
             name, registered, record["images"],
             "n/a" if record["mean_reprojection_error"] is None else f"{record['mean_reprojection_error']:.2f} px",
             record["points"], record["seconds"])
    if record["other_models"]:
        log.warning("%s: the images form %d disconnected models; the largest (%d images) is used, left out: %s",
                    name, 1 + len(record["other_models"]), registered,
                    "; ".join(f"{len(group)} images of another ({_names(group)})" for group in record["other_models"]))
    if record["left_out"]:
        log.info("%s: not registered: %s", name, _why_left_out(record))


def _require_registered(record: dict, where: Path, views: int, test_every: int) -> None:
    needed = images_needed(views, test_every)
    registered = len(record["registered"])
    if registered < needed:
        why = _why_left_out(record)
        raise ConfigError("capture.views",
                          f"{views}: structure-from-motion registered {registered} of {record['images']} images of "
                          f"{where}{f' ({why})' if why else ''}, and {views} training views plus the held-out ones "
                          f"need {needed}; ask for fewer views, or add photos that overlap the others")


def sharpness(frame: np.ndarray) -> float:
    """Variance of the Laplacian of a frame's grey levels: low for a blurred frame."""
    from skimage.color import rgb2gray
    from skimage.filters import laplace

    return float(laplace(rgb2gray(frame[..., :3])).var())


def sample_frames(video: Path, count: int, out: Path) -> list[Path]:
    """The sharpest frame of each of ``count`` equal windows of ``video`` (every frame when it has fewer), written
    as PNGs named by their frame number into ``out``; read with imageio's ffmpeg plugin."""
    import imageio.v3 as iio
    import imageio_ffmpeg

    if count < 1:
        raise ConfigError("capture.frames", f"{count}: sample at least {MIN_IMAGES} frames")
    try:
        total, _ = imageio_ffmpeg.count_frames_and_secs(str(video))
    except (OSError, RuntimeError) as error:
        raise InputFileError(video, f"cannot read the video ({one_line(error)})",
                             "give a video file ffmpeg reads (mp4, mov, mkv, ...)") from error
    windows = min(count, total)
    out.mkdir(parents=True)
    written: list[Path] = []
    best: tuple[float, int, np.ndarray] | None = None
    window = 0

    def keep(choice: tuple[float, int, np.ndarray]) -> None:
        path = out / f"frame_{choice[1]:06d}.png"
        iio.imwrite(path, choice[2][..., :3])
        written.append(path)

    for index, frame in enumerate(iio.imiter(video, plugin="FFMPEG")):
        if index >= total:
            break
        if index * windows // total != window:
            keep(best)
            best, window = None, index * windows // total
        score = sharpness(frame)
        if best is None or score > best[0]:
            best = (score, index, frame)
    if best is not None:
        keep(best)
    log.info("%s: %d frames, kept the sharpest of each of %d windows", video.name, total, len(written))
    return written
