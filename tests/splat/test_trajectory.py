"""Deployment trajectories: clip anchoring, look-at orientation, smoothness, round dependence."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import ring_cameras

from tracegs.splat.config import TrajectoryConfig
from tracegs.splat.trajectory import (
    bridge_poses,
    clip_layout,
    ellipse_poses,
    focus_point,
    make_clip,
    round_shape,
    round_trajectory,
    shorter_arc,
)


def viewing_angle_to(camera, point) -> float:
    """Angle (degrees) between the optical axis and the direction to `point`."""
    direction = point - camera.center
    cosine = (camera.rotation[2] @ direction) / direction.norm()
    return math.degrees(math.acos(min(1.0, cosine.item())))


def assert_proper_rotation(camera):
    rotation = camera.rotation.double()
    assert torch.allclose(rotation @ rotation.T, torch.eye(3, dtype=torch.float64), atol=1e-5)
    assert torch.linalg.det(rotation).item() == pytest.approx(1.0, abs=1e-5)


def observed_views():
    # Eight views on a wavy ring looking at the origin, shifted so the focus is not at the world origin.
    shift = torch.tensor([0.5, -0.3, 0.2])
    cameras = ring_cameras(8)
    for camera in cameras:
        camera.world_to_camera[:3, 3] -= camera.rotation @ shift
    return cameras, shift


def test_focus_point_is_where_the_axes_meet():
    cameras, shift = observed_views()
    assert torch.allclose(focus_point(cameras), shift, atol=1e-4)


def test_ellipse_is_closed_and_looks_at_the_focus():
    cameras, shift = observed_views()
    poses = ellipse_poses(cameras, 48, scale=0.8, height_variation=0.2, phase=1.0)
    assert len(poses) == 48
    for pose in poses:
        assert_proper_rotation(pose)
        assert viewing_angle_to(pose, shift) < 0.05
    centres = torch.stack([pose.center for pose in poses])
    steps = (centres.roll(-1, dims=0) - centres).norm(dim=1)  # includes the wrap-around step
    assert steps.max() < 1.5 * steps.mean()
    horizontal = (centres - shift)[:, :2].norm(dim=1)
    assert horizontal.mean() == pytest.approx(0.8 * 3.5, rel=0.05)  # scale x the cameras' ring radius
    heights = centres[:, 2] - shift[2]
    assert heights.max() - heights.min() > 0.2 * 2 * 3.5 * 0.8  # vertical variation is applied


def test_clip_is_anchored_by_reference_views_and_smooth():
    cameras, shift = observed_views()
    path = ellipse_poses(cameras, 64, scale=1.0, height_variation=0.1, phase=0.3)[:9]
    clip = make_clip(cameras[0], cameras[1], path, 49)
    assert len(clip) == 49 and clip_layout(49) == (16, 17, 16)
    assert torch.allclose(clip[0].world_to_camera, cameras[0].world_to_camera, atol=1e-5)
    assert torch.allclose(clip[-1].world_to_camera, cameras[1].world_to_camera, atol=1e-5)
    radius = (cameras[0].center - shift).norm()
    for previous, current in zip(clip[:-1], clip[1:]):
        assert_proper_rotation(current)
        assert (current.center - previous.center).norm() < 0.1 * radius
        relative = current.rotation @ previous.rotation.T
        angle = math.degrees(math.acos(max(-1.0, min(1.0, (relative.trace().item() - 1) / 2))))
        assert angle < 5.0
    for pose in clip:
        assert viewing_angle_to(pose, shift) < 2.0


def test_bridge_interpolates_between_its_ends():
    cameras, _ = observed_views()
    bridge = bridge_poses(cameras[2], cameras[3], 4)
    assert torch.allclose(bridge[0].world_to_camera, cameras[2].world_to_camera, atol=1e-5)
    halfway = bridge_poses(cameras[2], cameras[3], 2)[1]
    assert torch.allclose(halfway.center, (cameras[2].center + cameras[3].center) / 2, atol=1e-5)


def test_round_trajectory_depends_on_round_and_phase():
    cameras, shift = observed_views()
    pairs = [(i, (i + 1) % 8) for i in range(8)]
    cfg = TrajectoryConfig(frames_per_clip=9, ellipse_scales=[1.0, 0.7], height_variations=[0.05, 0.2])
    round0 = round_trajectory(cameras, pairs, 0, cfg, torch.Generator().manual_seed(0))
    again = round_trajectory(cameras, pairs, 0, cfg, torch.Generator().manual_seed(0))
    other_phase = round_trajectory(cameras, pairs, 0, cfg, torch.Generator().manual_seed(1))
    round1 = round_trajectory(cameras, pairs, 1, cfg, torch.Generator().manual_seed(0))
    assert len(round0) == 8 and all(len(clip) == 9 for clip in round0)
    for clip, (a, b) in zip(round0, pairs):
        assert torch.allclose(clip[0].world_to_camera, cameras[a].world_to_camera, atol=1e-5)
        assert torch.allclose(clip[-1].world_to_camera, cameras[b].world_to_camera, atol=1e-5)

    def middle_centres(clips):
        return torch.stack([clip[4].center for clip in clips])

    assert torch.equal(middle_centres(round0), middle_centres(again))
    assert not torch.allclose(middle_centres(round0), middle_centres(other_phase), atol=1e-3)
    radius0 = (middle_centres(round0) - shift)[:, :2].norm(dim=1).mean()
    radius1 = (middle_centres(round1) - shift)[:, :2].norm(dim=1).mean()
    assert radius1 < 0.85 * radius0  # later rounds use the smaller ellipse scale
    # The eight clips together go once around the scene.
    angles = torch.atan2(*(middle_centres(round0) - shift)[:, [1, 0]].T)
    assert len(set(torch.floor((angles + math.pi) / (math.pi / 4)).long().tolist())) >= 6


def test_invalid_trajectory_arguments_raise():
    cameras, _ = observed_views()
    with pytest.raises(ValueError, match="at least 3"):
        clip_layout(2)
    with pytest.raises(ValueError, match="reference pair"):
        round_trajectory(cameras, [], 0, TrajectoryConfig())


def azimuth(camera, centre) -> float:
    offset = camera.center - centre
    return math.degrees(math.atan2(offset[1].item(), offset[0].item()))


def turned(path, centre) -> float:
    """Total signed azimuth (degrees) a camera path turns through around ``centre``."""
    angles = [azimuth(camera, centre) for camera in path]
    return sum((b - a + 180.0) % 360.0 - 180.0 for a, b in zip(angles, angles[1:]))


@pytest.mark.parametrize("order", ["forward", "backward"])
def test_each_clip_takes_the_shorter_arc_between_its_references(order):
    """Three views 120 degrees apart, chained against the ellipse's direction or with it: every clip must
    turn through about 120 degrees, never the 240-degree long way round."""
    cameras, shift = observed_views()
    three = [cameras[i] for i in (0, 3, 6)] if order == "forward" else [cameras[i] for i in (6, 3, 0)]
    cfg = TrajectoryConfig(frames_per_clip=49, ellipse_scales=[1.0], height_variations=[0.0])
    clips = round_trajectory(three, [(0, 1), (1, 2), (2, 0)], 0, cfg, torch.Generator().manual_seed(0))
    for clip in clips:
        assert abs(turned(clip, shift)) < 180.0, turned(clip, shift)


def test_shorter_arc_goes_either_way_and_once_round_for_one_pose():
    assert shorter_arc(1, 3, 8) == [1, 2, 3]
    assert shorter_arc(3, 1, 8) == [3, 2, 1]
    assert shorter_arc(7, 1, 8) == [7, 0, 1]
    assert len(shorter_arc(2, 2, 8)) == 9


def test_round_shapes_cycle_so_many_rounds_use_every_shape_equally():
    cfg = TrajectoryConfig(ellipse_scales=[1.0, 0.85, 0.7], height_variations=[0.05, 0.1, 0.15])
    shapes = [round_shape(cfg, r) for r in range(9)]
    assert {s: shapes.count(s) for s in shapes} == {(1.0, 0.05): 3, (0.85, 0.1): 3, (0.7, 0.15): 3}


def test_captured_ends_replace_the_rendered_end_frames():
    """GSFixer's release, gsfixer/extrapolation/outpaint/sparse.py l. 286-297: the clip's first and last frames
    are the captured reference images, the frames between them stay rendered."""
    from tracegs.splat.trajectory import with_captured_ends

    frames, references = torch.rand(5, 3, 4, 6), torch.rand(2, 3, 4, 6)
    clip = with_captured_ends(frames, references)
    assert torch.equal(clip[0], references[0]) and torch.equal(clip[-1], references[1])
    assert torch.equal(clip[1:-1], frames[1:-1])
    with pytest.raises(ValueError, match="rendered size"):
        with_captured_ends(frames, torch.rand(2, 3, 8, 12))
