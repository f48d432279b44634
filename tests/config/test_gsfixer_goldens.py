"""Ours against GSFixer's own functions (GVCLab/GSFixer 19e0216): the goldens ``benchmarks/gsfixer_crosscheck.py``
wrote by running them (its ``command`` is in the file), and, where ``TRACEGS_GSFIXER_RELEASE`` names a release
checkout, the live cross-check itself."""

from __future__ import annotations

import json
import math

import pytest
import torch

from benchmarks.gsfixer_crosscheck import ENV, GOLDENS, compare, make_goldens, release_root
from tracegs.splat.cameras import Camera
from tracegs.splat.trajectory import focus_ellipse, release_ellipse


@pytest.fixture(scope="module")
def goldens():
    return json.loads(GOLDENS.read_text())


def test_the_goldens_record_the_command_that_made_them(goldens):
    assert "benchmarks/gsfixer_crosscheck.py" in goldens["command"] and ENV in goldens["command"]


def test_ours_match_gsfixers_trajectory_windows_sparse_views_and_ssim(goldens):
    """Ellipse (its world, its poses there and in ours, rounds 0-2) within 1e-6, windows and sparse views exactly,
    SSIM of the same 8-bit images within 1e-6."""
    assert compare(goldens) == []


def cameras_of(case) -> list[Camera]:
    intrinsics = torch.tensor([[60.0, 0.0, 36.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    return [Camera.from_pose(intrinsics, torch.tensor(pose)[:, :3].T.contiguous().float(),
                             torch.tensor(pose)[:, 3].float(), 72, 48) for pose in case["camera_to_worlds"]]


@pytest.mark.parametrize("name", ["three", "twelve"])
def test_the_release_ellipse_as_cameras_is_gsfixers(goldens, name):
    """``release_ellipse`` (what ``ellipse_frame=gsfixer_world`` deploys) gives GSFixer's poses as our cameras,
    to float32 precision; the corrected ellipse (``focus``) does not."""
    case = goldens["ellipse"][name]
    cameras = cameras_of(case)
    for entry in case["rounds"]:
        args = (85, 1.2, entry["z_variation"], 2 * math.pi * entry["z_phase"], entry["pitch_degrees"])
        expected = torch.tensor(entry["in_our_world"])
        released = torch.stack([torch.cat([c.rotation.T, c.center[:, None]], 1) for c in release_ellipse(cameras, *args)])
        corrected = torch.stack([torch.cat([c.rotation.T, c.center[:, None]], 1) for c in focus_ellipse(cameras, *args)])
        assert (released - expected).abs().max() < 1e-4
        assert (corrected[:, :, 3] - expected[:, :, 3]).norm(dim=-1).max() > 0.05


def test_the_live_cross_check_agrees_with_the_committed_goldens(goldens):
    root = release_root()
    if root is None:
        pytest.skip(f"{ENV} is unset: no GSFixer release checkout to run (the goldens above stand in for it)")
    assert make_goldens(root) == goldens
    assert compare(goldens) == []
