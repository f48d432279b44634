"""`tracegs-restore` end to end on a capture written in COLMAP layout (the synthetic benchmark's writer), at
the smallest sizes, with the real tiny restorer freshly initialised (no trained weights needed)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import pytest

from tracegs.data.config import SyntheticConfig
from tracegs.data.synthetic import generate_scene
from tracegs.splat.ply import load_ply

RESTORE = Path(sys.executable).with_name("tracegs-restore")
SMALLEST = [
    "experiment.frame_height=24", "experiment.frame_width=32",
    "data.prepare.fit.iterations=40", "data.prepare.fit.snapshot_iters=[10,20,40]",
    "data.prepare.fit.densification.enabled=false",
    "deploy.total_iters=40", "deploy.repair_iters=[10,25]", "deploy.steps=2", "deploy.max_clips_per_round=1",
    "deploy.trajectory.ellipse_frames=24", "evaluation.video_frames=6", "evaluation.grid_views=2",
    "evaluation.progress=false",
]


def restore(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(RESTORE), f"paths.root_dir={tmp_path}", *overrides], cwd=tmp_path,
                          capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("captures")
    cfg = SyntheticConfig(root=str(root), num_views=16, height=24, width=32, num_objects=1,
                          gaussians_per_unit_area=150, init_points=400)
    return generate_scene(3, cfg, root)


def test_restore_writes_ply_video_grid_and_scores(capture, tmp_path):
    # ablation=A deploys the baseline restorer; with no baseline weights it is the randomly initialised
    # tiny backbone (what a user without trained weights has), run through the whole restore-refine loop.
    result = restore(tmp_path, f"capture.path={capture}", "capture.views=3", "ablation=A",
                     "artifacts.baseline_weights=null", *SMALLEST)
    assert result.returncode == 0, result.stderr[-3000:]
    (run,) = (tmp_path / "outputs" / "embedded" / "restore" / "A").iterdir()  # the run's identity folder
    results = json.loads((run / "results.json").read_text())
    assert set(results["3dgs"]) == set(results["baseline"]) == {"3"}
    assert 5.0 < results["baseline"]["3"]["psnr"] < 60.0
    unit = json.loads((run / "units" / capture.name / "views_3.json").read_text())
    assert len(unit["captured"]) == 3 and not set(unit["captured"]) & set(unit["test"])
    refined = load_ply(unit["models"]["baseline"])
    assert len(refined) > 0 and Path(unit["models"]["3dgs"]).is_file()
    grid = iio.imread(unit["media"]["grid"])
    assert grid.ndim == 3 and grid.shape[0] > 2 * 24  # caption strip + two held-out views
    assert Path(unit["media"]["video"]).stat().st_size > 0
    frames = sorted(Path(unit["media"]["frames"]["baseline"]).glob("frame_*.png"))
    assert len(frames) == 6 and iio.imread(frames[0]).shape == (24, 32, 3)
    assert f"refined 3DGS (baseline): {unit['models']['baseline']}" in result.stdout
    assert not list(run.rglob("*.tmp"))


def test_restore_names_a_missing_capture_in_one_line(tmp_path):
    result = restore(tmp_path, f"capture.path={tmp_path / 'no_such_scene'}")
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "capture.path" in lines[0] and "no_such_scene" in lines[0]
