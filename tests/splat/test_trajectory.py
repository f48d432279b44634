"""Deployment trajectories: clip anchoring, look-at orientation, smoothness, round dependence."""

from __future__ import annotations

import math

import pytest
import torch
from support.scenes import ring_cameras

from tracegs.errors import ConfigError
from tracegs.splat.cameras import Camera, look_at_rotation
from tracegs.splat.config import ClipRule, EllipseFrame, TrajectoryConfig
from tracegs.splat.trajectory import (
    bridge_poses,
    clip_layout,
    ellipse_poses,
    focus_ellipse,
    focus_point,
    gsfixer_bridge,
    make_clip,
    nearest_view,
    round_clips,
    round_shape,
    round_trajectory,
    shorter_arc,
    window_starts,
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


# GSFixer's windows (ClipRule.gsfixer_windows). The ring: eight cameras on an ellipse of semi-axes 3 x 2 at
# heights alternately +0.5 and -0.5, all looking at the origin, so the focus is the origin, the mean up is +z,
# the principal axes are x then y, the 90th-percentile offsets are 3 and 2 and the 10th-90th height band is +-0.5.
RING_SEMI_AXES, RING_HEIGHT = (3.0, 2.0), 0.5


def elliptic_ring() -> list[Camera]:
    cameras = []
    for k in range(8):
        theta = 2 * math.pi * k / 8
        eye = torch.tensor([RING_SEMI_AXES[0] * math.cos(theta), RING_SEMI_AXES[1] * math.sin(theta),
                            RING_HEIGHT * (-1) ** k])
        cameras.append(Camera.look_at(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]), fov_x_deg=50.0,
                                      width=72, height=48))
    return cameras


def gsfixer_config(**overrides) -> TrajectoryConfig:
    values = dict(frames_per_clip=49, ellipse_frames=85, clip_rule=ClipRule.gsfixer_windows,
                  ellipse_frame=EllipseFrame.focus,
                  ellipse_scales=[1.2, 1.2, 1.2], height_variations=[1.5, 1.3, 1.1], pitch_degrees=[0.0, 2.0, 4.0])
    return TrajectoryConfig(**{**values, **overrides})


def test_gsfixer_windows_start_where_gsfixer_cuts_its_85_poses():
    """gsfixer/extrapolation/outpaint/base.py l. 13-34 (generate_overlapping_indices with num_frames 49 // 3 + 1):
    85 poses give 7 windows of 17 starting at 0/12/24/36/48/60/68; 20 poses in windows of 4 give 7 windows, six
    overlapping by 1 and the last by 3."""
    assert window_starts(85, 17) == [0, 12, 24, 36, 48, 60, 68]
    assert window_starts(20, 4) == [0, 3, 6, 9, 12, 15, 16]
    with pytest.raises(ValueError, match="at least"):
        window_starts(16, 17)


def test_gsfixer_round_is_seven_clips_of_a_bridge_a_window_and_a_bridge():
    """gsfixer/extrapolation/outpaint/sparse.py l. 236-283: per window, 16 bridge poses from the reference (the
    last one the window's first pose), the window's 17 consecutive ellipse poses, 16 bridge poses to the
    reference (the first one the window's last pose): 49 frames, ends at the two references."""
    cameras = elliptic_ring()
    cfg = gsfixer_config()
    clips = round_clips(cameras, 0, cfg, None, torch.Generator().manual_seed(0))
    phase = 2 * math.pi * torch.rand((), generator=torch.Generator().manual_seed(0)).item()
    ellipse = focus_ellipse(cameras, 85, 1.2, 1.5, phase, 0.0)
    assert len(clips) == 7
    for ((a, b), clip), start in zip(clips, [0, 12, 24, 36, 48, 60, 68]):
        assert len(clip) == 49
        for frame, pose in zip(clip[16:33], ellipse[start:start + 17]):
            assert torch.allclose(frame.world_to_camera, pose.world_to_camera, atol=1e-6)
        assert torch.allclose(clip[15].world_to_camera, clip[16].world_to_camera, atol=1e-6)
        assert torch.allclose(clip[33].world_to_camera, clip[32].world_to_camera, atol=1e-6)
        assert torch.allclose(clip[0].world_to_camera, cameras[a].world_to_camera, atol=1e-5)
        assert torch.allclose(clip[-1].world_to_camera, cameras[b].world_to_camera, atol=1e-5)
        assert (a, b) == (nearest_view(cameras, clip[16]), nearest_view(cameras, clip[32]))


@pytest.mark.parametrize("round_index, multiple, pitch", [(0, 1.5, 0.0), (1, 1.3, 2.0), (2, 1.1, 4.0)])
def test_gsfixer_ellipse_height_and_pitch_per_round(round_index, multiple, pitch):
    """gsfixer/extrapolation/outpaint/sparse.py l. 198-204 (z_variation 1.5 - 0.2 r, scale=r) with
    sample_utils.py l. 144-219: pose k of 85 at angle t = 2 pi k / 85 sits at (1.2 x 3 cos t, 1.2 x 2 sin t,
    z_variation x (-0.5 + (0.5 cos(t + phase) + 0.5))) on the ring, looks at the origin pitched up by 2r degrees
    about its own x axis."""
    cameras = elliptic_ring()
    clips = round_clips(cameras, round_index, gsfixer_config(), None, torch.Generator().manual_seed(3))
    phase = 2 * math.pi * torch.rand((), generator=torch.Generator().manual_seed(3)).item()
    for (_, clip), start in zip(clips, window_starts(85, 17)):
        for k, pose in enumerate(clip[16:33], start):
            t = 2 * math.pi * k / 85
            height = multiple * (-RING_HEIGHT + 2 * RING_HEIGHT * (0.5 * math.cos(t + phase) + 0.5))
            expected = torch.tensor([1.2 * RING_SEMI_AXES[0] * math.cos(t), 1.2 * RING_SEMI_AXES[1] * math.sin(t),
                                     height])
            assert torch.allclose(pose.center, expected, atol=1e-4), (k, pose.center, expected)
            assert_proper_rotation(pose)
            level = look_at_rotation(expected, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
            assert torch.allclose(pose.rotation[0], level[0], atol=1e-5)  # pitched about its own x axis
            up_tilted = math.cos(math.radians(pitch)) * level[2] - math.sin(math.radians(pitch)) * level[1]
            assert torch.allclose(pose.rotation[2], up_tilted, atol=1e-5)  # towards the camera's up (-y)


def test_gsfixer_bridge_keeps_gsfixers_uneven_last_step():
    """gsfixer/extrapolation/outpaint/sparse.py l. 26-39 and l. 80-81: interp_traj of two poses samples the
    spline at k / 16 for k < 15 and appends the end pose, so centres 0..14 then 16 between x = 0 and x = 16; the
    optical axis is the normalised blend of the two ends (l. 63-72)."""
    start = Camera.look_at(torch.zeros(3), torch.tensor([0.0, 5.0, 0.0]), torch.tensor([0.0, 0.0, 1.0]),
                           fov_x_deg=50.0, width=72, height=48)
    end = Camera.look_at(torch.tensor([16.0, 0.0, 0.0]), torch.tensor([21.0, 0.0, 0.0]),
                         torch.tensor([0.0, 0.0, 1.0]), fov_x_deg=50.0, width=72, height=48)
    bridge = gsfixer_bridge(start, end, 16, start)
    assert [round(pose.center[0].item(), 4) for pose in bridge] == [*range(15), 16]
    assert torch.allclose(bridge[0].world_to_camera, start.world_to_camera, atol=1e-6)
    assert torch.allclose(bridge[-1].world_to_camera, end.world_to_camera, atol=1e-6)
    halfway = gsfixer_bridge(start, end, 3, start)[1]  # fraction 1/3
    blend = torch.tensor([1 / 3, 2 / 3, 0.0]) / torch.tensor([1 / 3, 2 / 3, 0.0]).norm()
    assert torch.allclose(halfway.rotation[2], blend, atol=1e-6)
    for pose in bridge:
        assert_proper_rotation(pose)


def test_each_window_bridges_to_the_view_gsfixers_score_prefers():
    """gsfixer/extrapolation/outpaint/sparse.py l. 157-172: score = centre distance + 0.5 x (1 - cosine of the
    optical axes). From a pose at the origin looking along +x: a view 0.8 away looking back scores 1.8, one 0.9
    away looking sideways 1.4, one 1.0 away looking the same way 1.0, so the farthest one is chosen."""
    up = torch.tensor([0.0, 0.0, 1.0])

    def view(centre, direction):
        centre = torch.tensor(centre)
        return Camera.look_at(centre, centre + torch.tensor(direction), up, fov_x_deg=50.0, width=72, height=48)

    pose = view([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    views = [view([0.0, 0.8, 0.0], [-1.0, 0.0, 0.0]), view([0.0, -0.9, 0.0], [0.0, 1.0, 0.0]),
             view([-1.0, 0.0, 0.0], [1.0, 0.0, 0.0])]
    assert nearest_view(views, pose) == 2
    assert nearest_view(views[:2], pose) == 1


def test_gsfixer_windows_refuse_what_they_cannot_make():
    with pytest.raises(ConfigError, match="'frames_per_clip'.*at least 7"):
        gsfixer_config(frames_per_clip=5).validate()
    with pytest.raises(ConfigError, match="'ellipse_frames'"):
        gsfixer_config(ellipse_frames=16).validate()
    with pytest.raises(ConfigError, match="'pitch_degrees'"):
        TrajectoryConfig(pitch_degrees=[2.0]).validate()
    with pytest.raises(ConfigError, match="'height_variations'"):
        gsfixer_config(height_variations=[]).validate()


def test_gsfixer_windows_capped_per_round_are_a_subset_of_the_round():
    """``max_clips`` keeps a random subset of a round's windows, in window order (the rehearsal restores one)."""
    every = round_clips(elliptic_ring(), 0, gsfixer_config(), None, torch.Generator().manual_seed(3))
    two = round_clips(elliptic_ring(), 0, gsfixer_config(), 2, torch.Generator().manual_seed(3))
    assert len(two) == 2 and len(every) > 2
    def centres(cams):
        return torch.stack([camera.center for camera in cams])

    positions = [next(i for i, (_, cams) in enumerate(every) if torch.equal(centres(cams), centres(clip)))
                 for _, clip in two]
    assert positions == sorted(set(positions)) and all(every[i][0] == pair for i, (pair, _) in zip(positions, two))
