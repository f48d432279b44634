"""`tracegs-restore` end to end on a capture written in COLMAP layout (the synthetic benchmark's writer), at
the smallest sizes, with the real tiny restorer freshly initialised (no trained weights needed)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import imageio.v3 as iio
import pytest
from support.report_page import checked_page
from support.restores import RESTORE_A, restore, runs, small_capture

from tracegs.splat.ply import load_ply


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return small_capture(tmp_path_factory.mktemp("captures"))


@pytest.fixture(scope="module")
def restored(capture, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """(launch folder, result) of one restore of ``capture`` (variant A, support.restores)."""
    root = tmp_path_factory.mktemp("restore")
    result = restore(root, *RESTORE_A, f"capture.path={capture}")
    assert result.returncode == 0, result.stderr[-3000:]
    return root, result


def test_restore_writes_ply_video_grid_and_scores(capture, restored):
    root, result = restored
    (run,) = runs(root)  # the run's identity folder
    results = json.loads((run / "results.json").read_text())
    assert set(results["3dgs"]) == set(results["baseline"]) == {"3"}
    assert 5.0 < results["baseline"]["3"]["psnr"] < 60.0
    unit = json.loads((run / "units" / capture.name / "views_3.json").read_text())
    assert len(unit["captured"]) == 3 and not set(unit["captured"]) & set(unit["test"])
    # The unit names its files relative to the run folder, so the folder can be copied or moved.
    refined = load_ply(run / unit["models"]["baseline"])
    assert len(refined) > 0 and (run / unit["models"]["3dgs"]).is_file()
    grid = iio.imread(run / unit["media"]["grid"])
    assert grid.ndim == 3 and grid.shape[0] > 2 * 24  # caption strip + two held-out views
    assert (run / unit["media"]["video"]).stat().st_size > 0
    frames = sorted((run / unit["media"]["frames"]["baseline"]).glob("frame_*.png"))
    assert len(frames) == 6 and iio.imread(frames[0]).shape == (24, 32, 3)
    # The cameras of the views fitted to and scored on, with their images, for tracegs-view.
    assert set(unit["cameras"]) == {str(view) for view in unit["captured"] + unit["test"]}
    assert iio.imread(run / unit["cameras"][str(unit["test"][0])]["image"]).shape == (24, 32, 3)
    assert f"refined 3DGS (baseline): {run.resolve() / unit['models']['baseline']}" in result.stdout
    assert not list(run.rglob("*.tmp"))


def test_restore_shows_its_tables_grid_video_and_plys_on_one_page(capture, restored):
    """``report.html`` opens from the copied or moved run folder: its links are the folder's own files."""
    root, result = restored
    (run,) = runs(root)
    _, links = checked_page(run, "table.md")
    unit = json.loads((run / "units" / capture.name / "views_3.json").read_text())
    assert {unit["media"]["grid"], unit["media"]["video"], *unit["models"].values()} <= set(links)
    assert f"report: {(run / 'report.html').resolve()}" in result.stdout


@pytest.mark.slow  # restores a capture twice more (~17 s); the identity rules are unit-tested in tests/config
def test_a_copied_capture_is_the_same_run_and_an_edited_one_recomputes(capture, restored, tmp_path):
    """The capture is known by its images and reconstruction: a copy elsewhere reuses the finished run; an image
    replaced in the copy makes a new run, which scores the edited capture."""
    root, _ = restored
    (run,) = runs(root)
    unit_file = run / "units" / capture.name / "views_3.json"
    finished = unit_file.read_bytes(), unit_file.stat().st_mtime_ns
    copy = tmp_path / "moved" / capture.name
    shutil.copytree(capture, copy)
    again = restore(root, *RESTORE_A, f"capture.path={copy}")
    assert again.returncode == 0, again.stderr[-3000:]
    assert runs(root) == [run] and (unit_file.read_bytes(), unit_file.stat().st_mtime_ns) == finished
    image = sorted((copy / "images").iterdir())[0]
    iio.imwrite(image, 255 - iio.imread(image))
    edited = restore(root, *RESTORE_A, f"capture.path={copy}")
    assert edited.returncode == 0, edited.stderr[-3000:]
    (new_run,) = set(runs(root)) - {run}
    assert json.loads((new_run / "units" / capture.name / "views_3.json").read_text())["methods"] != json.loads(
        finished[0])["methods"]


def test_restore_names_a_missing_capture_in_one_line(tmp_path):
    result = restore(tmp_path, f"capture.path={tmp_path / 'no_such_scene'}")
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "capture.path" in lines[0] and "no_such_scene" in lines[0]
