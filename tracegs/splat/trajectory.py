"""Deployment camera trajectories (supplement A.5): a 360-degree ellipse around the scene's focus point plus
bridge poses to the observed reference views, cut into clips whose first and last frames are the references."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from kornia.geometry.quaternion import Quaternion
from torch import Tensor

from tracegs.splat.cameras import Camera, look_at_rotation
from tracegs.splat.config import ClipRule, EllipseFrame, TrajectoryConfig


def focus_point(cameras: Sequence[Camera]) -> Tensor:
    """The point nearest (least squares) to all optical axes; the centres' mean if the axes are parallel."""
    centres = torch.stack([camera.center.double() for camera in cameras])
    forwards = torch.stack([camera.rotation[2].double() for camera in cameras])
    return _nearest_to_axes(centres, forwards).float()


def _nearest_to_axes(centres: Tensor, forwards: Tensor) -> Tensor:
    """The point [3] (float64) nearest in least squares to the lines through ``centres`` [N,3] along
    ``forwards`` [N,3]; the centres' mean if the lines are parallel."""
    projectors = torch.eye(3, dtype=torch.float64) - forwards[:, :, None] * forwards[:, None, :]
    system = projectors.sum(dim=0)
    rhs = (projectors @ centres[:, :, None]).sum(dim=0)
    if torch.linalg.matrix_rank(system, atol=1e-6 * len(centres)) < 3:
        return centres.mean(dim=0)
    return torch.linalg.solve(system, rhs)[:, 0]


def mean_up(cameras: Sequence[Camera]) -> Tensor:
    """Average world-space 'up' (camera -y) direction, normalised."""
    up = -torch.stack([camera.rotation[1] for camera in cameras]).float().mean(dim=0)
    return up / up.norm().clamp_min(1e-12)


def ellipse_poses(cameras: Sequence[Camera], n: int, scale: float = 1.0, height_variation: float = 0.0,
                  phase: float = 0.0, focus: Tensor | None = None) -> list[Camera]:
    """`n` cameras on a closed ellipse around `focus` (default `focus_point(cameras)`), all looking at it.

    The ellipse lies in the plane through the cameras' mean height, perpendicular to their mean up direction;
    its axes follow the principal directions of the camera centres and its semi-axes are `scale` times their
    spread (at least half the mean distance). The height oscillates once around the loop with amplitude
    `height_variation` x the mean horizontal distance, shifted by `phase` (radians). Pose 0 sits at the angle
    of the first camera. Intrinsics and image size come from `cameras[0]`.
    """
    if n < 1:
        raise ValueError(f"ellipse_poses needs n >= 1, got {n}")
    focus = focus_point(cameras) if focus is None else focus.float()
    up = mean_up(cameras)
    offsets = torch.stack([camera.center.float() for camera in cameras]) - focus
    heights = offsets @ up
    planar = offsets - heights[:, None] * up
    mean_distance = planar.norm(dim=1).mean().clamp_min(1e-6)
    # Principal horizontal axes of the camera centres; fall back to any horizontal basis for one camera.
    basis = torch.linalg.svd(planar, full_matrices=True).Vh if len(cameras) > 1 else None
    axis_u = basis[0] if basis is not None else planar[0]
    axis_u = axis_u - (axis_u @ up) * up
    if axis_u.norm() < 1e-6:
        axis_u = torch.linalg.cross(up, torch.tensor([1.0, 0.0, 0.0]))
        if axis_u.norm() < 1e-6:
            axis_u = torch.linalg.cross(up, torch.tensor([0.0, 1.0, 0.0]))
    axis_u = axis_u / axis_u.norm()
    axis_v = torch.linalg.cross(up, axis_u)
    coord_u, coord_v = planar @ axis_u, planar @ axis_v
    semi_u = scale * max((2.0 * coord_u.square().mean()).sqrt().item(), 0.5 * mean_distance.item())
    semi_v = scale * max((2.0 * coord_v.square().mean()).sqrt().item(), 0.5 * mean_distance.item())
    start = math.atan2(coord_v[0].item() / semi_v, coord_u[0].item() / semi_u)
    base_height = heights.mean().item()
    reference = cameras[0]
    poses = []
    for k in range(n):
        theta = start + 2.0 * math.pi * k / n
        height = base_height + height_variation * mean_distance.item() * math.sin(theta - start + phase)
        eye = focus + semi_u * math.cos(theta) * axis_u + semi_v * math.sin(theta) * axis_v + height * up
        poses.append(Camera.from_pose(reference.K.float(), look_at_rotation(eye, focus, up), eye, reference.width,
                                      reference.height))
    return poses


def interpolate_pose(cam_a: Camera, cam_b: Camera, t: float) -> Camera:
    """Pose a fraction `t` of the way from `cam_a` to `cam_b`: slerped rotation, linearly interpolated centre
    and intrinsics."""
    rotation = Quaternion.from_matrix(cam_a.rotation.double()).slerp(
        Quaternion.from_matrix(cam_b.rotation.double()), t).matrix().float()
    centre = torch.lerp(cam_a.center.float(), cam_b.center.float(), t)
    intrinsics = torch.lerp(cam_a.K.float(), cam_b.K.float(), t)
    return Camera.from_pose(intrinsics, rotation, centre, cam_a.width, cam_a.height)


def bridge_poses(cam_a: Camera, cam_b: Camera, n: int) -> list[Camera]:
    """`n` evenly spaced poses from `cam_a` (included) towards `cam_b` (excluded)."""
    if n < 0:
        raise ValueError(f"bridge_poses needs n >= 0, got {n}")
    return [interpolate_pose(cam_a, cam_b, k / n) for k in range(n)]


def resample_path(path: Sequence[Camera], n: int) -> list[Camera]:
    """`n` poses evenly spaced (in path index) along the polyline of `path`, both ends included."""
    if len(path) == 1 or n == 1:
        return [path[0]] * n
    poses = []
    for position in torch.linspace(0, len(path) - 1, n).tolist():
        index = min(int(position), len(path) - 2)
        poses.append(interpolate_pose(path[index], path[index + 1], position - index))
    return poses


def clip_layout(num_frames: int) -> tuple[int, int, int]:
    """Frames per (bridge, path, bridge) segment: 16/17/16 at 49 frames (GSFixer), 2/5/2 at 9."""
    if num_frames < 3:
        raise ValueError(f"a clip needs at least 3 frames, got {num_frames}")
    bridge = (num_frames - 1) // 3
    return bridge, num_frames - 2 * bridge, bridge


def make_clip(ref_a: Camera, ref_b: Camera, path: Sequence[Camera], num_frames: int) -> list[Camera]:
    """A clip that starts at `ref_a`, bridges onto `path` (resampled evenly), and bridges off it to end at
    `ref_b`: `clip_layout(num_frames)` frames per segment."""
    if not path:
        raise ValueError("make_clip needs a non-empty path")
    head, middle, tail = clip_layout(num_frames)
    segment = resample_path(path, middle)
    leaving = bridge_poses(ref_b, segment[-1], tail)[::-1]
    clip = bridge_poses(ref_a, segment[0], head) + segment + leaving
    if head == 0:
        clip[0] = ref_a
    if tail == 0:
        clip[-1] = ref_b
    return clip


def with_captured_ends(frames: Tensor, references: Tensor) -> Tensor:
    """A rendered clip [F,3,H,W] whose first and last frames are replaced by the two captured reference images
    [2,3,H,W] of its end cameras (GSFixer's release, gsfixer/extrapolation/outpaint/sparse.py l. 286-297)."""
    if references.shape[0] != 2 or references.shape[1:] != frames.shape[1:]:
        raise ValueError(f"references {tuple(references.shape)} do not match a clip of frames "
                         f"{tuple(frames.shape[1:])}: two captured images at the rendered size are needed")
    return torch.cat([references[:1].to(frames), frames[1:-1], references[1:].to(frames)])


def _nearest(poses: Sequence[Camera], camera: Camera) -> int:
    centres = torch.stack([pose.center for pose in poses])
    return int((centres - camera.center.float()).norm(dim=1).argmin())


def reference_pairs(num_views: int, max_clips: int | None, generator: torch.Generator) -> list[tuple[int, int]]:
    """Reference-view pairs of one round: the views chained in capture order and closed into a loop
    ((v0, v1), ..., (v_{K-1}, v0)), so the round's clips cover the whole ellipse; with ``max_clips`` a random
    subset per round (rounds then cover different arcs)."""
    if num_views < 2:
        raise ValueError(f"clips need two reference views, but only {num_views} view is given")
    pairs = [(i, (i + 1) % num_views) for i in range(num_views)] if num_views > 2 else [(0, 1), (1, 0)]
    return random_subset(pairs, max_clips, generator)


def random_subset(items: list, count: int | None, generator: torch.Generator) -> list:
    """``count`` of ``items`` drawn from ``generator``, in their order (all of them when ``count`` is None or not
    smaller)."""
    if count is None or count >= len(items):
        return items
    keep = torch.randperm(len(items), generator=generator)[:count].sort().values.tolist()
    return [items[i] for i in keep]


def shorter_arc(start: int, stop: int, n: int) -> list[int]:
    """Indices of a closed loop of ``n`` poses from ``start`` to ``stop`` (both included) the shorter way
    round; once around the loop when both are the same pose."""
    forward, backward = (stop - start) % n, (start - stop) % n
    if forward == 0:
        return [(start + k) % n for k in range(n + 1)]
    step, length = (1, forward) if forward <= backward else (-1, backward)
    return [(start + step * k) % n for k in range(length + 1)]


def round_shape(cfg: TrajectoryConfig, round_index: int) -> tuple[float, float]:
    """(ellipse scale, height variation) of repair round ``round_index`` (0-based). The lists give one entry
    per repair round and cycle beyond them, so prepare's many rounds per scene use the deployment rounds'
    shapes in equal measure."""
    if round_index < 0:
        raise ValueError(f"round_index must be >= 0, got {round_index}")
    return (cfg.ellipse_scales[round_index % len(cfg.ellipse_scales)],
            cfg.height_variations[round_index % len(cfg.height_variations)])


def round_trajectory(references: Sequence[Camera], pairs: Sequence[tuple[int, int]], round_index: int,
                     cfg: TrajectoryConfig, generator: torch.Generator | None = None) -> list[list[Camera]]:
    """Clips of repair round ``round_index`` (supplement A.5), the one rule prepare and deployment share.

    The round's ellipse is fitted to the reference views ``references`` (the captured V_s at deployment, a
    training clip's own K-view set in prepare), with the round's scale and height variation (``round_shape``) and a
    random vertical phase drawn from ``generator``. Per pair (a, b) of indices into ``references``, one clip
    from reference a to reference b whose middle follows the ellipse the shorter way round from the pose
    nearest a to the pose nearest b. Chained pairs (``reference_pairs``) cover the whole 360 degrees.
    """
    if not pairs:
        raise ValueError("round_trajectory needs at least one reference pair")
    scale, variation = round_shape(cfg, round_index)
    phase = 2.0 * math.pi * torch.rand((), generator=generator).item()
    ellipse = ellipse_poses(references, cfg.ellipse_frames, scale, variation, phase)
    clips = []
    for a, b in pairs:
        arc = shorter_arc(_nearest(ellipse, references[a]), _nearest(ellipse, references[b]), len(ellipse))
        clips.append(make_clip(references[a], references[b], [ellipse[i] for i in arc], cfg.frames_per_clip))
    return clips


def focus_ellipse(cameras: Sequence[Camera], n: int, scale: float, height_multiple: float, phase: float,
                    pitch_degrees: float) -> list[Camera]:
    """GSFixer's ellipse of ``n`` poses (gsfixer/extrapolation/outpaint/sample_utils.py l. 144-219) corrected to
    the cameras' own frame (``ellipse_frame=focus``): origin at the focus point, height along the cameras' mean up
    direction, in-plane axes the principal axes of the camera centres (largest spread first, signed so that the
    first camera lies on the positive side). The release (``release_ellipse``) instead centres its ellipse on
    1.2 x the focus point's world xy and measures heights from world z = 0, so the ellipse moves with the
    world's origin. Pose k sits at angle 2 pi k / n from
    the first axis, on semi-axes ``scale`` x the 90th percentile of the centres' absolute offsets along each axis
    (l. 158-161); its height is ``height_multiple`` x a point of the centres' 10th-90th percentile height band,
    swept once around the loop with phase ``phase`` radians (l. 165-183). Every pose looks at the focus point,
    level with the cameras' mean up (l. 198-203), then turns up about its own x axis by ``pitch_degrees``
    (l. 204-217, ``scale=i`` there). Intrinsics and image size come from ``cameras[0]`` (sparse.py l. 124).
    """
    focus = focus_point(cameras)
    up = mean_up(cameras)
    offsets = torch.stack([camera.center.float() for camera in cameras]) - focus
    heights = offsets @ up
    planar = offsets - heights[:, None] * up
    spread = planar - planar.mean(dim=0)
    axes = torch.linalg.eigh(spread.T @ spread).eigenvectors.flip(-1).T  # descending spread
    axis_x = axes[0] if (planar[0] @ axes[0]) >= 0 else -axes[0]
    axis_y = torch.linalg.cross(up, axis_x)
    semi_x, semi_y = (scale * torch.quantile((planar @ axis).abs(), 0.9).item() for axis in (axis_x, axis_y))
    low, high = torch.quantile(heights, 0.1).item(), torch.quantile(heights, 0.9).item()
    pitch = math.radians(pitch_degrees)
    turn = torch.tensor([[1.0, 0.0, 0.0],
                         [0.0, math.cos(pitch), math.sin(pitch)],
                         [0.0, -math.sin(pitch), math.cos(pitch)]])
    reference = cameras[0]
    poses = []
    for k in range(n):
        theta = 2.0 * math.pi * k / n
        height = height_multiple * (low + (high - low) * (0.5 * math.cos(theta + phase) + 0.5))
        eye = focus + semi_x * math.cos(theta) * axis_x + semi_y * math.sin(theta) * axis_y + height * up
        rotation = turn @ look_at_rotation(eye, focus, up)
        poses.append(Camera.from_pose(reference.K.float(), rotation, eye, reference.width, reference.height))
    return poses


def cameras_to_worlds(cameras: Sequence[Camera]) -> Tensor:
    """Camera-to-world matrices [N,3,4] (float64, OpenCV axes: x right, y down, z forward), GSFixer's pose
    layout (sparse.py l. 192-197)."""
    return torch.stack([torch.cat([camera.rotation.double().T, camera.center.double()[:, None]], dim=1)
                        for camera in cameras])


def gsfixer_world(camera_to_worlds: Tensor) -> Tensor:
    """The similarity [4,4] (float64) taking a world to GSFixer's normalised one as its camera step computes it
    (datasets/normalize.py l. 4-63, ``similarity_from_cameras`` with its defaults, called at colmap_debug.py
    l. 199-201): z along the cameras' mean up (their -y axes), origin at the median of each optical axis's point
    nearest the old origin, unit median camera distance. GSFixer then turns the world to the principal axes of
    the scene's whole SfM point cloud (normalize.py l. 66-97, colmap_debug.py l. 204-206); deployment holds no
    such cloud, so that turn about the up axis is not made."""
    rotations, centres = camera_to_worlds[:, :, :3], camera_to_worlds[:, :, 3]
    world_up = -rotations[:, :, 1].mean(dim=0)
    world_up = world_up / world_up.norm()
    camera_up = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    cosine = camera_up @ world_up
    cross = torch.linalg.cross(world_up, camera_up)
    skew = torch.tensor([[0.0, -cross[2], cross[1]], [cross[2], 0.0, -cross[0]], [-cross[1], cross[0], 0.0]],
                        dtype=torch.float64)
    if cosine > -1:
        align = torch.eye(3, dtype=torch.float64) + skew + skew @ skew / (1 + cosine)
    else:  # the cameras' mean up is +y: a half turn about x (normalize.py l. 33-36)
        align = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    forwards = (align @ rotations)[:, :, 2]
    centres = centres @ align.T
    nearest = centres + ((forwards * -centres).sum(dim=-1))[:, None] * forwards
    translate = -torch.quantile(nearest, 0.5, dim=0)  # np.median: the mean of the middle two
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, :3], transform[:3, 3] = align, translate
    transform[:3] /= torch.quantile((centres + translate).norm(dim=-1), 0.5)
    return transform


def transform_cameras(transform: Tensor, camera_to_worlds: Tensor) -> Tensor:
    """Camera-to-world matrices [N,3,4] moved by the similarity ``transform`` [4,4], rotations kept orthonormal
    (GSFixer's datasets/normalize.py l. 115-130)."""
    moved = transform[:3, :3] @ camera_to_worlds
    moved[:, :, 3] += transform[:3, 3]
    moved[:, :, :3] /= moved[:, 0, :3].norm(dim=-1)[:, None, None]
    return moved


def gsfixer_ellipse_path(camera_to_worlds: Tensor, n: int, z_variation: float, z_phase: float,
                         pitch_degrees: float, scale: float = 1.2) -> Tensor:
    """GSFixer's ``generate_ellipse_path`` (gsfixer/extrapolation/outpaint/sample_utils.py l. 144-218) on its
    camera-to-world poses [N,3,4] (float64): ``n`` poses [n,3,4] on world axes. The centre is ``scale`` (1.2 in the
    release, l. 160-161) x the focus point's world xy, the semi-axes ``scale`` x the 90th percentile of the
    centres' absolute offsets from the focus's xy (l. 158); the height is ``z_variation`` x a point of the
    centres' 10th-90th percentile world-z band, swept once round with phase ``z_phase`` turns (l. 165-183), in
    absolute world z. Each pose looks at the focus with its y axis the world axis nearest the cameras' mean y
    (l. 197-203), then turns about its own x axis by ``pitch_degrees`` (l. 204-217: 2 x its ``scale`` argument,
    the round index). The sign drawn at l. 205 is never applied, so every round pitches the same way."""
    centres = camera_to_worlds[:, :, 3]
    focus = _nearest_to_axes(centres, camera_to_worlds[:, :, 2])
    offset = torch.stack([focus[0], focus[1], torch.zeros((), dtype=torch.float64)])
    spread = torch.quantile((centres - offset).abs(), 0.9, dim=0)
    low, high = (offset - spread) * scale, (offset + spread) * scale
    z_low, z_high = torch.quantile(centres[:, 2], 0.1), torch.quantile(centres[:, 2], 0.9)
    theta = torch.linspace(0.0, 2.0 * math.pi, n + 1, dtype=torch.float64)[:-1]
    positions = torch.stack([
        low[0] + (high - low)[0] * (torch.cos(theta) * 0.5 + 0.5),
        low[1] + (high - low)[1] * (torch.sin(theta) * 0.5 + 0.5),
        z_variation * (z_low + (z_high - z_low) * (torch.cos(theta + 2.0 * math.pi * z_phase) * 0.5 + 0.5)),
    ], dim=-1)
    mean_y = camera_to_worlds[:, :, 1].mean(dim=0)
    axis = int(mean_y.abs().argmax())
    world_y = torch.zeros(3, dtype=torch.float64)
    world_y[axis] = torch.sign(mean_y[axis])
    forward = torch.nn.functional.normalize(focus - positions, dim=-1)
    right = torch.nn.functional.normalize(torch.linalg.cross(world_y.expand_as(forward), forward), dim=-1)
    down = torch.nn.functional.normalize(torch.linalg.cross(forward, right), dim=-1)
    pitch = math.radians(pitch_degrees)
    turn = torch.tensor([[1.0, 0.0, 0.0],
                         [0.0, math.cos(pitch), -math.sin(pitch)],
                         [0.0, math.sin(pitch), math.cos(pitch)]], dtype=torch.float64)
    return torch.cat([torch.stack([right, down, forward], dim=-1) @ turn, positions[:, :, None]], dim=-1)


def release_ellipse(cameras: Sequence[Camera], n: int, scale: float, height_multiple: float, phase: float,
                    pitch_degrees: float) -> list[Camera]:
    """GSFixer's ellipse as released (``ellipse_frame=gsfixer_world``): ``gsfixer_ellipse_path`` in GSFixer's
    normalised world (``gsfixer_world`` of the cameras), mapped back to ours. ``phase`` is in radians (GSFixer
    draws it in turns, sparse.py l. 199). Intrinsics and image size come from ``cameras[0]`` (sparse.py l. 124)."""
    poses = cameras_to_worlds(cameras)
    world = gsfixer_world(poses)
    path = gsfixer_ellipse_path(transform_cameras(world, poses), n, height_multiple, phase / (2.0 * math.pi),
                                pitch_degrees, scale)
    path = transform_cameras(torch.linalg.inv(world), path).float()
    reference = cameras[0]
    return [Camera.from_pose(reference.K.float(), pose[:, :3].T.contiguous(), pose[:, 3], reference.width,
                             reference.height) for pose in path]


def window_starts(total: int, window: int) -> list[int]:
    """First pose of each of GSFixer's overlapping windows of ``window`` consecutive poses over a path of
    ``total`` (gsfixer/extrapolation/outpaint/base.py l. 13-34): total // window + 2 windows sharing the surplus
    as evenly spaced overlaps, the last window taking the remainder; 0/12/24/36/48/60/68 for 85 poses in
    windows of 17."""
    if not 1 <= window <= total:
        raise ValueError(f"windows of {window} poses need a path of at least that many, got {total}")
    count = total // window + 2
    overlap = count * window - total
    if overlap < count:
        overlap += count
    step = window - overlap // (count - 1)
    starts = [k * step for k in range(count - 1)]
    return [*starts, starts[-1] + window - (overlap - (count - 2) * (overlap // (count - 1)))]


def nearest_view(views: Sequence[Camera], pose: Camera) -> int:
    """Index of the view nearest ``pose`` by GSFixer's score, the distance between centres plus 0.5 x (1 -
    cosine between the optical axes) (gsfixer/extrapolation/outpaint/sparse.py l. 146-173); the first on ties."""
    centres = torch.stack([view.center.float() for view in views])
    forwards = torch.stack([view.rotation[2].float() for view in views])
    scores = (centres - pose.center.float()).norm(dim=1) + 0.5 * (1.0 - forwards @ pose.rotation[2].float())
    return int(scores.argmin())


def gsfixer_bridge(start: Camera, end: Camera, n: int, intrinsics: Camera) -> list[Camera]:
    """GSFixer's ``n`` bridge poses from ``start`` to ``end``, both included (gsfixer/extrapolation/outpaint/
    sparse.py l. 26-111, ``interp_traj`` of two poses): the fractions k / n for k < n - 1, then ``end`` itself.
    Centres are interpolated linearly; the optical axis is the normalised blend of the two, the x axis
    perpendicular to it and to the blended y axes (their look-at and up points, interpolated linearly). Image
    size and intrinsics come from ``intrinsics``."""
    if n < 2:
        raise ValueError(f"a bridge includes both ends, so n >= 2, got {n}")
    poses = []
    for t in [k / n for k in range(n - 1)] + [1.0]:
        forward = torch.lerp(start.rotation[2].float(), end.rotation[2].float(), t)
        forward = forward / forward.norm()
        right = torch.linalg.cross(torch.lerp(start.rotation[1].float(), end.rotation[1].float(), t), forward)
        right = right / right.norm()
        rotation = torch.stack([right, torch.linalg.cross(forward, right), forward])
        centre = torch.lerp(start.center.float(), end.center.float(), t)
        poses.append(Camera.from_pose(intrinsics.K.float(), rotation, centre, intrinsics.width, intrinsics.height))
    return poses


def window_clips(references: Sequence[Camera], round_index: int, cfg: TrajectoryConfig,
                 generator: torch.Generator) -> list[tuple[tuple[int, int], list[Camera]]]:
    """(reference pair, cameras) of every clip of round ``round_index`` by GSFixer's rule (``clip_rule`` =
    ``gsfixer_windows``; gsfixer/extrapolation/outpaint/sparse.py l. 191-283): the round's ellipse
    (``release_ellipse`` or ``focus_ellipse`` by ``cfg.ellipse_frame``, with the round's scale, height multiple and
    pitch and a vertical phase drawn from ``generator``, l. 198-204) cut into ``window_starts`` windows of the middle segment's poses and bridged by the
    end segments' (``clip_layout``: 16/17/16 at 49 frames, l. 246-253) from the view nearest its first pose
    (``nearest_view``) and to the view nearest its last one (l. 249-283). A window's first and last ellipse poses also end its bridges, as
    in GSFixer; the pair is (view before, view after), possibly one view twice."""
    scale, height_multiple = round_shape(cfg, round_index)
    pitch = cfg.pitch_degrees[round_index % len(cfg.pitch_degrees)]
    phase = 2.0 * math.pi * torch.rand((), generator=generator).item()
    ellipse_rule = release_ellipse if cfg.ellipse_frame == EllipseFrame.gsfixer_world else focus_ellipse
    ellipse = ellipse_rule(references, cfg.ellipse_frames, scale, height_multiple, phase, pitch)
    bridge, length, _ = clip_layout(cfg.frames_per_clip)
    clips = []
    for start in window_starts(len(ellipse), length):
        window = ellipse[start:start + length]
        a, b = nearest_view(references, window[0]), nearest_view(references, window[-1])
        clip = (gsfixer_bridge(references[a], window[0], bridge, references[0]) + window
                + gsfixer_bridge(window[-1], references[b], bridge, references[0]))
        clips.append(((a, b), clip))
    return clips


def round_clips(references: Sequence[Camera], round_index: int, cfg: TrajectoryConfig, max_clips: int | None,
                generator: torch.Generator) -> list[tuple[tuple[int, int], list[Camera]]]:
    """(reference pair, cameras) of every clip of round ``round_index`` given the K reference views, by
    ``cfg.clip_rule``: GSFixer's windows (``window_clips``; with ``max_clips`` a random subset of them, drawn after
    the windows), or the round's pairs (``reference_pairs``) and their clips (``round_trajectory``), drawn in that
    order from ``generator``. Deployment calls it with the captured views, prepare with a training clip's K-view
    set."""
    if cfg.clip_rule == ClipRule.gsfixer_windows:
        return random_subset(window_clips(references, round_index, cfg, generator), max_clips, generator)
    pairs = reference_pairs(len(references), max_clips, generator)
    return list(zip(pairs, round_trajectory(references, pairs, round_index, cfg, generator)))


def clips_per_round(cfg: TrajectoryConfig, num_views: int, max_clips: int | None) -> int:
    """How many clips ``round_clips`` makes a round from ``num_views`` reference views: GSFixer's windows (7 for
    85 poses in windows of 17), or one per reference pair (``reference_pairs``); at most ``max_clips``."""
    if cfg.clip_rule == ClipRule.gsfixer_windows:
        count = len(window_starts(cfg.ellipse_frames, clip_layout(cfg.frames_per_clip)[1]))
    else:
        count = len(reference_pairs(num_views, None, torch.Generator()))
    return count if max_clips is None else min(count, max_clips)
