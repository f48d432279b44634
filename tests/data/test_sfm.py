"""Structure-from-motion for captures without a COLMAP model (tracegs.data.sfm), with the real pycolmap on photos
of a procedural scene rendered with the CPU rasterizer (benchmarks/sfm.py builds it: the embedded benchmark's
shapes, textured for SIFT), through the photo path and through ``tracegs-restore`` itself."""

from __future__ import annotations

import json
import logging
import shutil
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image
from skimage.filters import gaussian
from support.inputs import TINY_RESTORE, assert_refused, files_under

from tracegs.data.colmap import load_scene
from tracegs.data.config import SceneSourceConfig, SfmConfig
from tracegs.data.sfm import (
    MAX_CAMERA_REPROJECTION_PX,
    MAX_ROTATION_DISAGREEMENT_DEG,
    RECORD,
    reconstruct_photos,
    sample_frames,
    sharpness,
    strongest_pair_medians,
    working_photos,
)
from tracegs.errors import InputFileError

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from sfm import camera_errors, orbit, render_frames, textured_scene, write_photos  # noqa: E402

# One thread: the suite runs a test per core.
SFM = {"threads": 1}


@pytest.fixture(scope="module")
def model():
    return textured_scene()


@pytest.fixture(scope="module")
def thirty_photos(model, tmp_path_factory) -> tuple[Path, dict]:
    """30 photos along the embedded benchmark's orbit at 320x240, and each one's true camera."""
    capture = tmp_path_factory.mktemp("capture") / "garden"
    return capture, write_photos(capture, model, orbit(30))


@pytest.fixture(scope="module")
def reconstructed(thirty_photos, tmp_path_factory) -> Path:
    capture, _ = thirty_photos
    return reconstruct_photos(capture, SfmConfig(dir=str(tmp_path_factory.mktemp("captures")), **SFM), views=6,
                              test_every=8)


def test_photos_give_the_true_cameras_up_to_a_similarity(thirty_photos, reconstructed):
    """The acceptance bound: after a similarity alignment of the centres, every registered camera within 1 degree
    of its true orientation and 2% of the scene's extent of its true centre (measured: 0.57 deg, 0.92%)."""
    _, truth = thirty_photos
    errors = camera_errors(reconstructed, truth)
    assert errors["registered_fraction"] == 1.0
    assert errors["rotation_error_deg"] <= 1.0, errors
    assert errors["center_error_rel"] <= 0.02, errors


def test_the_reconstruction_is_an_undistorted_scene_folder_with_its_record(reconstructed):
    import pycolmap

    model = pycolmap.Reconstruction(str(reconstructed / "sparse" / "0"))
    assert {camera.model.name for camera in model.cameras.values()} == {"PINHOLE"}
    assert sorted(p.name for p in (reconstructed / "images").iterdir()) == sorted(
        image.name for image in model.images.values())
    record = json.loads((reconstructed / RECORD).read_text())
    assert len(record["registered"]) == record["images"] == 30 and record["left_out"] == {}
    assert 0 < record["mean_reprojection_error"] < 1.0 and record["cameras"] == [[320, 240]]
    assert not [p for p in reconstructed.parent.iterdir() if p.name.startswith(".")]  # no work files kept


def test_a_rerun_reuses_the_reconstruction_and_a_changed_photo_makes_another(thirty_photos, reconstructed, tmp_path,
                                                                            caplog):
    capture, _ = thirty_photos
    cfg = SfmConfig(dir=str(reconstructed.parents[1]), **SFM)
    stamp = (reconstructed / RECORD).stat().st_mtime_ns
    with caplog.at_level(logging.INFO, logger="tracegs.data.sfm"):
        assert reconstruct_photos(capture, cfg, views=6, test_every=8) == reconstructed
    assert (reconstructed / RECORD).stat().st_mtime_ns == stamp and "reusing the reconstruction" in caplog.text
    edited = tmp_path / capture.name
    edited.mkdir()
    for photo in sorted(capture.iterdir())[:12]:  # a smaller capture keeps this quick
        (edited / photo.name).write_bytes(photo.read_bytes())
    first = reconstruct_photos(edited, cfg, views=3, test_every=8)
    image = edited / "photo_000.png"
    iio.imwrite(image, np.ascontiguousarray(iio.imread(image)[:, ::-1]))
    second = reconstruct_photos(edited, cfg, views=3, test_every=8)
    assert first != second and first.is_dir() and (second / RECORD).is_file()


def files_of(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_renamed_capture_gets_the_same_reconstruction_without_making_it_again(thirty_photos, reconstructed,
                                                                               tmp_path, caplog):
    """The reconstruction is keyed by the photos, not the folder's name: a renamed copy gets the same cameras and
    points, byte for byte (a second run of COLMAP on several threads would not repeat to the bit)."""
    capture, _ = thirty_photos
    renamed = tmp_path / "salon"
    shutil.copytree(capture, renamed)
    with caplog.at_level(logging.INFO, logger="tracegs.data.sfm"):
        scene = reconstruct_photos(renamed, SfmConfig(dir=str(reconstructed.parents[1]), **SFM), views=6,
                                   test_every=8)
    assert scene.parent == reconstructed.parent and scene.name == "salon" and "copied from" in caplog.text
    assert files_of(scene) == files_of(reconstructed)


def test_a_large_photo_is_downsized_once_and_a_truncated_one_is_named(model, tmp_path):
    """Photos longer than the size SfM works at are read reduced (JPEG draft) and written at it, upright; a photo
    that does not decode whole is refused, named, before COLMAP could read its top and fill the rest with grey."""
    photos = tmp_path / "photos"
    write_photos(photos, model, orbit(2, arc_deg=20.0))
    large = Image.open(photos / "photo_000.png").resize((1600, 1200))
    exif = large.getexif()
    exif[0x0112] = 6  # held upright
    large.save(photos / "photo_000.jpg", exif=exif, quality=95)
    (photos / "photo_000.png").unlink()
    names = ["photo_000.jpg", "photo_001.png"]
    working = working_photos(photos, names, tmp_path / "working", longest=400)
    assert Image.open(working / "photo_000.jpg").size == (300, 400)  # upright, downsized
    assert (working / "photo_001.png").resolve() == photos / "photo_001.png"  # small enough: linked as it is
    data = (photos / "photo_000.jpg").read_bytes()
    (photos / "photo_000.jpg").write_bytes(data[: len(data) * 2 // 5])
    with pytest.raises(InputFileError, match="photo_000.jpg: cannot decode the photo"):
        working_photos(photos, names, tmp_path / "again", longest=2000)


def test_other_files_are_ignored_aloud_and_photos_of_two_sizes_are_checked_before_they_are_trusted(
        model, tmp_path, caplog):
    """Each size gets its camera, and the model of two cameras is checked (each camera's reprojection, each view
    against its strongest photo pairs' own rotations): this one is right (every camera within 1.1 deg of the
    truth, measured), and the check passes it with what it measured on record."""
    capture = tmp_path / "mixed" / "images"  # photos in an images/ folder of the capture
    truth = write_photos(capture, model, orbit(14, arc_deg=140.0))
    for photo in sorted(capture.iterdir())[1::2]:  # every other photo at another size (another camera)
        Image.open(photo).resize((400, 300)).save(photo)
    (capture / "notes.txt").write_text("taken at noon")
    Image.open(capture / "photo_000.png").save(capture / "extra.webp")  # a format COLMAP's reader skips
    with caplog.at_level(logging.INFO, logger="tracegs.data.sfm"):
        scene = reconstruct_photos(capture.parent, SfmConfig(dir=str(tmp_path / "captures"), **SFM), views=3,
                                   test_every=8)
    assert "ignored 2 file(s) that are not photos (extra.webp, notes.txt)" in caplog.text
    record = json.loads((scene / RECORD).read_text())
    assert record["cameras"] == [[320, 240], [400, 300]]
    assert max(record["consistency"]["reprojection_error_px"].values()) <= MAX_CAMERA_REPROJECTION_PX
    assert record["consistency"]["rotation_disagreement_deg"] <= MAX_ROTATION_DISAGREEMENT_DEG
    assert camera_errors(scene, truth)["rotation_error_deg"] <= 2.0


def test_a_view_is_judged_by_its_strongest_pairs():
    """A right view whose weak pairs' own two-view rotations are wrong passes (measured on the 14 photos above:
    photo_000's pairs, by inlier matches, with their disagreement in degrees); a view placed 55 degrees off
    disagrees with its strong pairs too and is caught."""
    right = [(100, 3.2), (25, 5.4), (25, 64.7), (59, 85.6), (20, 105.1), (157, 2.1), (59, 6.5), (29, 56.3),
             (49, 75.3), (30, 100.1), (16, 131.4)]
    misplaced = [(inliers, 55.0 + angle / 10.0) for inliers, angle in right]
    medians = strongest_pair_medians({"right.png": right, "misplaced.png": misplaced})
    assert medians["right.png"] <= MAX_ROTATION_DISAGREEMENT_DEG < medians["misplaced.png"]


def test_photos_taken_upright_are_reconstructed_as_the_loader_reads_them(model, tmp_path):
    """A phone held upright stores landscape pixels and an EXIF orientation; the loader turns them upright
    (tracegs.data.images), so the reconstruction must be of the upright photos."""
    capture = tmp_path / "phone"
    write_photos(capture, model, orbit(12, arc_deg=120.0))
    for photo in sorted(capture.iterdir()):
        image = Image.open(photo)
        exif = image.getexif()
        exif[0x0112] = 6  # rotated 90 degrees clockwise to view
        image.save(photo.with_suffix(".jpg"), exif=exif, quality=95)
        photo.unlink()
    scene = reconstruct_photos(capture, SfmConfig(dir=str(tmp_path / "captures"), scene_size=200, **SFM), views=3,
                               test_every=8)
    loaded = load_scene(SceneSourceConfig(root=str(scene.parent), preset="custom"), scene.name)
    assert len(loaded) == 12 and {(c.width < c.height) for c in loaded.cameras} == {True}
    assert max(c.height for c in loaded.cameras) <= 200  # undistorted at the scene's size, not the photos'
    assert loaded.load_image(0).shape[1:] == (loaded.cameras[0].height, loaded.cameras[0].width)


def test_disconnected_models_keep_the_largest_and_name_the_rest(model, tmp_path, caplog):
    """Two scenes with nothing in common: the one with more photos is reconstructed, the other is named."""
    capture = tmp_path / "two_places"
    write_photos(capture, model, orbit(8, arc_deg=80.0), prefix="a")
    elsewhere = textured_scene(ground=(("moon", "page"), ("text", "camera")),
                               wall=("retina", "immunohistochemistry", "clock", "colorwheel", "cell", "horse"))
    write_photos(capture, elsewhere, orbit(6, arc_deg=60.0, seed=11), prefix="b")
    with caplog.at_level(logging.INFO, logger="tracegs.data.sfm"):
        scene = reconstruct_photos(capture, SfmConfig(dir=str(tmp_path / "captures"), **SFM), views=3, test_every=8)
    record = json.loads((scene / RECORD).read_text())
    assert record["registered"] and all(name.startswith("a_") for name in record["registered"]), record
    left = [name for group in record["other_models"] for name in group]
    assert left and all(name.startswith("b_") for name in left)
    assert "disconnected models; the largest" in caplog.text and left[0] in caplog.text


def test_the_sharpest_frame_of_each_window_is_kept(model, tmp_path):
    frames = render_frames(model, orbit(12, arc_deg=60.0))
    # Each window of three holds one sharp frame between two blurred ones.
    blurred = [frame if i % 3 == 1 else (gaussian(frame, sigma=2, channel_axis=-1, preserve_range=True)).astype(np.uint8) for i, frame in enumerate(frames)]
    video = tmp_path / "clip.mp4"
    iio.imwrite(video, np.stack(blurred), plugin="FFMPEG", fps=6, quality=9)
    kept = sample_frames(video, 4, tmp_path / "frames")
    assert [p.name for p in kept] == [f"frame_{i:06d}.png" for i in (1, 4, 7, 10)]
    assert sharpness(iio.imread(kept[0])) > 2 * sharpness(blurred[0])


# --- bad captures through the real entry point: exit 2, one line naming the file or field, nothing written ---
TINY = [*TINY_RESTORE, "capture.sfm.threads=1"]


def two_photos(model, inputs: Path):
    write_photos(inputs / "pair", model, orbit(2, arc_deg=20.0))
    return [f"capture.path={inputs / 'pair'}"], f"{inputs / 'pair'}: 2 photos (photo_000.png, photo_001.png); " \
                                                 "structure-from-motion needs at least 3"


def too_few_registered(model, inputs: Path):
    """Five photos of the scene and four of noise, which match nothing: 9 photos pass the count, 5 register."""
    folder = inputs / "noisy"
    write_photos(folder, model, orbit(5, arc_deg=50.0))
    rng = np.random.default_rng(0)
    for index in range(4):
        Image.fromarray(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)).save(folder / f"noise_{index}.png")
    return ([f"capture.path={folder}", "capture.views=6"],
            f"config field 'capture.views': 6: structure-from-motion registered 5 of 9 images of {folder} (4 without "
            "matches to any other: noise_0.png, noise_1.png, noise_2.png, noise_3.png), and 6 training views plus "
            "the held-out ones need 7")


def close_ups(model, cameras, folder: Path, zoom: float) -> None:
    """Photos of the middle 1/``zoom`` of each camera's view enlarged to the full size, as a camera zoomed in on a
    small part of the scene would take them: SIFT matches them with a few features of the other photos only."""
    folder.mkdir(parents=True, exist_ok=True)
    for index, frame in enumerate(render_frames(model, cameras)):
        height, width = frame.shape[:2]
        crop_height, crop_width = int(height / zoom), int(width / zoom)
        top, left = (height - crop_height) // 2, (width - crop_width) // 2
        middle = Image.fromarray(frame[top:top + crop_height, left:left + crop_width])
        middle.resize((width, height), Image.BICUBIC).save(folder / f"close_{index}.png")


def too_little_overlap(model, inputs: Path):
    """Five photos of the scene and three close-ups taken further along the walk: each close-up has too few
    verified matches with the five registered photos for the mapper to place it (measured with pycolmap 4.2.1,
    one thread, fixed seeds: 20 at most)."""
    folder = inputs / "closeups"
    cameras = orbit(8, arc_deg=80.0)
    write_photos(folder, model, cameras[:5])
    close_ups(model, cameras[5:], folder, zoom=3.0)
    # The count of verified matches varies by one between machines and loads (19-20 seen), so the line is checked
    # up to it.
    return ([f"capture.path={folder}", "capture.views=6"],
            f"config field 'capture.views': 6: structure-from-motion registered 5 of 8 images of {folder} (3 with "
            "too little overlap to be placed, at most ")


def nothing_to_start_from(model, inputs: Path):
    """Three close-ups alone: two match, too little for the mapper to start a model from (it starts from a pair
    with 100 verified matches, relaxed to 25 when nothing else starts), and the third matches neither."""
    folder = inputs / "zoomed"
    close_ups(model, orbit(3, arc_deg=30.0), folder, zoom=2.5)
    return ([f"capture.path={folder}", "capture.views=2"],
            f"config field 'capture.views': 2: structure-from-motion registered 0 of 3 images of {folder} (2 "
            "matched, but with no pair the mapper could start a model from, at most 20 verified matches with any "
            "other image: close_0.png, close_1.png; 1 without matches to any other: close_2.png), and 2 "
            "training views plus the held-out ones need 3")


def fewer_photos_than_views(model, inputs: Path):
    write_photos(inputs / "four", model, orbit(4, arc_deg=40.0))
    return ([f"capture.path={inputs / 'four'}", "capture.views=6"],
            f"config field 'capture.views': 6: {inputs / 'four'} gives 4 photos, and 6 training views plus the "
            "held-out ones (every 8th image) need 7")


def video_of_two_frames(model, inputs: Path):
    return [f"capture.video={inputs / 'any.mp4'}", "capture.frames=2"], \
        "config field 'capture.frames': 2: structure-from-motion needs at least 3 frames"


def video_too_short(model, inputs: Path):
    """Its frames are sampled (into the reconstruction's temporary folder) before the count is known."""
    video = inputs / "blink.mp4"
    iio.imwrite(video, np.stack(render_frames(model, orbit(2, arc_deg=10.0))), plugin="FFMPEG", fps=2)
    return [f"capture.video={video}"], (f"{video}: 2 frames (frame_000000.png, frame_000001.png); "
                                        "structure-from-motion needs at least 3; give a longer video")


def not_a_video(model, inputs: Path):
    (inputs / "clip.mp4").write_text("not a video")
    return [f"capture.video={inputs / 'clip.mp4'}"], f"{inputs / 'clip.mp4'}: cannot read the video"


def path_and_video(model, inputs: Path):
    return [f"capture.path={inputs}", f"capture.video={inputs / 'clip.mp4'}"], \
        "config field 'capture.video': set either capture.path"


def truncated_photo(model, inputs: Path):
    """A JPEG cut to 40% of its bytes: COLMAP would read its top, fill the rest with grey and register it."""
    folder = inputs / "cut"
    write_photos(folder, model, orbit(5, arc_deg=50.0))
    photo = folder / "photo_002.jpg"
    Image.open(folder / "photo_002.png").save(photo, quality=95)
    (folder / "photo_002.png").unlink()
    photo.write_bytes(photo.read_bytes()[: photo.stat().st_size * 2 // 5])
    return ([f"capture.path={folder}", "capture.views=3"],
            f"{photo}: cannot decode the photo (image file is truncated")


BAD = {f.__name__: f for f in (truncated_photo, two_photos, too_few_registered, too_little_overlap, nothing_to_start_from,
                               fewer_photos_than_views, video_of_two_frames, video_too_short, not_a_video,
                               path_and_video)}


@pytest.mark.parametrize("case", list(BAD))
def test_a_bad_capture_gives_one_line_exit_2_and_writes_nothing(model, tmp_path, entry_point, case):
    inputs, root = tmp_path / "inputs", tmp_path / "root"
    inputs.mkdir()
    root.mkdir()
    overrides, expected = BAD[case](model, inputs)
    before = files_under(tmp_path)
    result = entry_point("restore", [*TINY, *overrides, f"paths.root_dir={root}"], root)
    assert_refused(result, "restore", expected, files_under(tmp_path) - before)
    assert list(root.iterdir()) == []  # not even a run folder or an empty captures folder


# --- end to end through tracegs-restore (slow: structure-from-motion, then the restore-refine loop) ---
SMALLEST = ["ablation=A", "artifacts.baseline_weights=null", "experiment.frame_height=24",
            "experiment.frame_width=32", "data.prepare.fit.iterations=40", "data.prepare.fit.snapshot_iters=[10,20,40]",
            "data.prepare.fit.densification.enabled=false", "deploy.total_iters=40", "deploy.repair_iters=[10,25]",
            "deploy.steps=2", "deploy.max_clips_per_round=1", "deploy.trajectory.ellipse_frames=24",
            "evaluation.video_frames=6", "evaluation.grid_views=2", "evaluation.progress=false",
            "capture.sfm.threads=1", "capture.views=3", "capture.size=32"]


def assert_restored(result, root: Path, scene: str) -> dict:
    """The restore succeeded and scored the reconstructed scene; returns its unit record."""
    assert result.returncode == 0, result.stderr[-3000:]
    (run,) = (root / "outputs" / "embedded" / "restore" / "A").iterdir()
    unit = json.loads((run / "units" / scene / "views_3.json").read_text())
    assert (run / unit["models"]["baseline"]).is_file() and (run / unit["media"]["video"]).stat().st_size > 0
    results = json.loads((run / "results.json").read_text())
    assert 5.0 < results["baseline"]["3"]["psnr"] < 60.0
    return unit


@pytest.mark.slow  # structure-from-motion of 30 photos, a restore and its rerun: 10 s on an idle core
def test_photos_restore_end_to_end_and_a_rerun_reuses_both(thirty_photos, tmp_path, entry_point):
    capture, _ = thirty_photos
    result = entry_point("restore", [*SMALLEST, f"capture.path={capture}", f"paths.root_dir={tmp_path}"], tmp_path)
    unit = assert_restored(result, tmp_path, capture.name)
    assert len(unit["test"]) == 4  # every 8th of the 30 registered photos is held out
    assert "registered 30 of 30 images, mean reprojection error" in result.stdout
    again = entry_point("restore", [*SMALLEST, f"capture.path={capture}", f"paths.root_dir={tmp_path}"], tmp_path)
    assert again.returncode == 0 and "reusing the reconstruction" in again.stdout
    assert len(list((tmp_path / "data" / "captures").iterdir())) == 1


@pytest.mark.slow  # a 90-frame video, 24 frames reconstructed in sequence, then a restore: 10 s on an idle core
def test_a_video_restores_end_to_end(model, tmp_path, entry_point):
    video = tmp_path / "walkaround.mp4"
    iio.imwrite(video, np.stack(render_frames(model, orbit(90))), plugin="FFMPEG", fps=15, quality=9)
    result = entry_point("restore", [*SMALLEST, f"capture.video={video}", "capture.frames=24",
                                     f"paths.root_dir={tmp_path}"], tmp_path)
    unit = assert_restored(result, tmp_path, "walkaround")
    assert len(unit["captured"]) == 3 and "sequential matching" in result.stdout
    (frames,) = (tmp_path / "data" / "captures").glob("*/frames")
    assert len(list(frames.iterdir())) == 24


def halved(capture: Path) -> None:
    for photo in sorted(capture.iterdir())[1::2]:
        Image.open(photo).resize((360, 240)).save(photo)


@pytest.mark.slow  # structure-from-motion of 12 photos at 720x480, then a restore: ~20 s on an idle core
def test_photos_of_two_sizes_give_a_checked_model_or_a_refusal_naming_the_sizes(model, tmp_path, entry_point):
    """12 photos of 720x480, every other one halved: two cameras, and the model they give is either right (every
    camera within a degree of its true orientation) or refused in one line naming the sizes, with nothing kept;
    never a wrong model in silence."""
    capture = tmp_path / "inputs" / "room"
    truth = write_photos(capture, model, orbit(12, 720, 480, arc_deg=140.0))
    halved(capture)
    root = tmp_path / "root"
    root.mkdir()
    result = entry_point("restore", [*SMALLEST, f"capture.path={capture}", f"paths.root_dir={root}"], root)
    if result.returncode == 2:
        (line,) = result.stderr_lines()
        assert "photos of 2 sizes (360x240, 720x480), one camera each" in line
        assert list(root.iterdir()) == []
        return
    assert_restored(result, root, "room")
    (scene,) = (root / "data" / "captures").glob("*/room")
    assert json.loads((scene / RECORD).read_text())["cameras"] == [[360, 240], [720, 480]]
    assert camera_errors(scene, truth)["rotation_error_deg"] <= 1.0


@pytest.mark.slow  # structure-from-motion of 12 photos and two restores: ~25 s on an idle core
def test_a_renamed_capture_restores_to_the_same_bytes(model, tmp_path, entry_point):
    """Only the photos' content and the seeds drive a restore: the same photos in a folder of another name give
    the same scores and the same refined 3DGS, byte for byte."""
    first = tmp_path / "inputs" / "garden"
    write_photos(first, model, orbit(12, arc_deg=140.0))
    second = tmp_path / "inputs" / "jardin"
    shutil.copytree(first, second)
    units = []
    for capture in (first, second):
        result = entry_point("restore", [*SMALLEST, f"capture.path={capture}", f"paths.root_dir={tmp_path}"],
                             tmp_path)
        units.append(assert_restored(result, tmp_path, capture.name))
    (run,) = (tmp_path / "outputs" / "embedded" / "restore" / "A").iterdir()
    assert units[0]["methods"] == units[1]["methods"]
    assert all((run / units[0]["models"][m]).read_bytes() == (run / units[1]["models"][m]).read_bytes()
               for m in units[0]["models"])


@pytest.mark.slow  # structure-from-motion of 12 photos at 720x480, then a restore at 360 px in tiles: ~2 min
def test_a_capture_of_portrait_and_landscape_photos_restores_at_360_px_with_each_aspect(model, tmp_path, entry_point):
    """720x480 photos with three of them portrait (the same lens held upright): one scene of two cameras, fitted,
    restored (the restorer's 48x72 frames in tiles) and scored at 360 px on the longer side, each view at its own
    orientation, none squashed."""
    capture = tmp_path / "inputs" / "room"
    portrait = {3, 6, 8}  # 8 is held out (every 8th view): a portrait view is scored
    write_photos(capture, model, [camera.reframed(480, 720) if index in portrait else camera
                                  for index, camera in enumerate(orbit(12, 720, 480, arc_deg=140.0))])
    at_size = [override for override in SMALLEST if not override.startswith(("capture.size", "experiment.frame"))]
    result = entry_point("restore", [*at_size, f"capture.path={capture}", f"paths.root_dir={tmp_path}"], tmp_path)
    unit = assert_restored(result, tmp_path, "room")
    (scene,) = (tmp_path / "data" / "captures").glob("*/room")
    assert json.loads((scene / RECORD).read_text())["cameras"] == [[480, 720], [720, 480]]
    sizes = {unit["names"][view]: tuple(camera["size"]) for view, camera in unit["cameras"].items()}
    assert any(unit["names"][str(view)] == "photo_008.png" for view in unit["test"])
    for name, (height, width) in sizes.items():  # each view at 360 px on its longer side, its own way up, 2:3
        upright = int(name[6:9]) in portrait  # (undistortion trims a pixel or two)
        assert max(height, width) == 360 and (height > width) == upright, name
        assert abs(min(height, width) / 360 - 2 / 3) < 0.01, name
    (run,) = (tmp_path / "outputs" / "embedded" / "restore" / "A").iterdir()
    for camera in unit["cameras"].values():
        assert iio.imread(run / camera["image"]).shape[:2] == tuple(camera["size"])
    held_out = unit["methods"]["baseline"]["per_view"]
    assert len(held_out) == len(unit["test"]) and all(5.0 < row["psnr"] < 60.0 for row in held_out)
