"""`tracegs-restore` at the smallest sizes on a capture written in COLMAP layout (the synthetic benchmark's
writer), for the tests that need a real restore folder: the restore's own tests and the viewer's."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tracegs.data.config import SyntheticConfig
from tracegs.data.synthetic import generate_scene

RESTORE = Path(sys.executable).with_name("tracegs-restore")
SMALLEST = [
    "experiment.frame_height=24", "experiment.frame_width=32",
    "data.prepare.fit.iterations=40", "data.prepare.fit.snapshot_iters=[10,20,40]",
    "data.prepare.fit.densification.enabled=false",
    "deploy.total_iters=40", "deploy.repair_iters=[10,25]", "deploy.steps=2", "deploy.max_clips_per_round=1",
    "deploy.trajectory.ellipse_frames=24", "evaluation.video_frames=6", "evaluation.grid_views=2",
    "evaluation.progress=false",
]
# ablation=A deploys the baseline restorer; with no baseline weights it is the randomly initialised tiny backbone
# (what a user without trained weights has), run through the whole restore-refine loop, beside plain 3DGS.
RESTORE_A = ("capture.views=3", "ablation=A", "artifacts.baseline_weights=null", *SMALLEST)


def small_capture(root: Path) -> Path:
    """A 16-view synthetic scene of 24 x 32 pixels in COLMAP layout under ``root``."""
    cfg = SyntheticConfig(root=str(root), num_views=16, height=24, width=32, num_objects=1,
                          gaussians_per_unit_area=150, init_points=400)
    return generate_scene(3, cfg, root)


def restore(root: Path, *overrides: str) -> subprocess.CompletedProcess:
    """``tracegs-restore`` with its folders under ``root``."""
    return subprocess.run([str(RESTORE), f"paths.root_dir={root}", *overrides], cwd=root,
                          capture_output=True, text=True, timeout=900)


def runs(root: Path) -> list[Path]:
    """The run folders of variant A's restores under ``root`` (one per capture identity)."""
    return sorted((root / "outputs" / "embedded" / "restore" / "A").iterdir())
