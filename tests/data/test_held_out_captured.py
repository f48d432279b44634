"""Held-out clips of a captured (COLMAP) scene: captured cameras between consecutive sparse views, the captured
images as ground truth (tracegs/data/held_out.py)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from scene_builders import tiny_configs, write_scene

from tracegs.data.colmap import load_scene
from tracegs.data.config import SceneSourceConfig, Split
from tracegs.data.held_out import NAME_ORDER, between_in_capture_order
from tracegs.data.images import to_uint8
from tracegs.data.preparation.driver import run_prepare
from tracegs.data.preparation.plan import PrepareError, plan_scene
from tracegs.data.preparation.shards import shard_is_valid
from tracegs.data.splits import split_scene
from tracegs.eval.clips import (
    INPUT,
    clip_restoration_psnr,
    held_out_clip_curves,
    held_out_clips,
    load_clip,
    mean_psnr,
    trajectory_frames,
    unit_curves,
    view_averaged_curves,
)
from tracegs.io import read_safetensors
from tracegs.restorer.sampler import RestorationPipeline


def held_out_configs(tmp_path, frames_per_clip: int = 5, views: tuple[int, ...] = (3, 6)):
    root, _ = write_scene(tmp_path / "scenes" / "ring", n=40)
    # Frames resized from the captured 36 x 24 to the configured 48 x 32, as a dataset's images are.
    source = SceneSourceConfig(root=str(root.parent), preset="custom", scenes=["ring"], height=32, width=48)
    _, _, tiny = tiny_configs(tmp_path)
    prepare = replace(tiny, split=Split.test, student_views=list(views), dense_views=[], student_final_fits=False,
                      pseudo_target="gt", frames_per_clip=frames_per_clip, store_frames=None)
    return source, prepare


def test_between_in_capture_order_wraps_around_for_the_closing_pair():
    assert between_in_capture_order(2, 6, 10, {4}) == [3, 5]
    assert between_in_capture_order(8, 1, 10, set()) == [9, 0]


def test_clips_run_through_captured_cameras_between_consecutive_sparse_views(tmp_path):
    source, prepare = held_out_configs(tmp_path)
    plan = plan_scene(source, prepare, "ring")
    scene = load_scene(source, "ring")
    assert [clip["views"] for clip in plan.captured] == [3] * 3 + [6] * 6  # every reference pair of every K
    for views in (3, 6):
        sparse = sorted(split_scene(scene, source, [views]).views(views))
        clips = [clip for clip in plan.captured if clip["views"] == views]
        # Pairs as deployment chains them: consecutive views in capture order, closed into a loop.
        assert [clip["refs"] for clip in clips] == [[sparse[i], sparse[(i + 1) % views]] for i in range(views)]
        for clip in clips:
            first, *interior, last = clip["images"]
            assert [first, last] == clip["refs"] and len(interior) == prepare.frames_per_clip - 2
            assert not set(interior) & set(sparse)
            # Capture order: each interior image lies after the previous one, going forward from the first view.
            offsets = [(i - first) % len(scene) for i in clip["images"]]
            assert offsets == sorted(set(offsets))
            for camera, index in zip(clip["cameras"], clip["images"]):
                assert torch.equal(camera.world_to_camera, scene.cameras[index].world_to_camera)
                assert torch.equal(camera.K, scene.cameras[index].K)


def test_scene_with_too_few_images_between_references_is_refused_before_any_work(tmp_path, backbone):
    source, prepare = held_out_configs(tmp_path, frames_per_clip=9, views=(9,))
    with pytest.raises(PrepareError, match=r"^scene ring: data\.prepare\.frames_per_clip=9 needs 7 captured images"):
        run_prepare(prepare, source, backbone, progress=False)
    assert not list((tmp_path / "cache").rglob("*.safetensors")) and not list((tmp_path / "work").rglob("*.ply"))


def test_repeating_frames_fills_a_clip_the_capture_is_too_short_for(tmp_path):
    source, prepare = held_out_configs(tmp_path, frames_per_clip=9, views=(9,))
    plan = plan_scene(source, replace(prepare, held_out_repeat_frames=True), "ring")
    sparse = sorted(split_scene(load_scene(source, "ring"), source, [9]).views(9))
    for clip in plan.captured:
        first, *interior, last = clip["images"]
        between = between_in_capture_order(first, last, 40, set(sparse))
        assert len(interior) == 7 and set(interior) == set(between)  # every captured image, some repeated
        assert [between.index(i) for i in interior] == sorted(between.index(i) for i in interior)


def test_held_out_cache_holds_the_captured_images_as_ground_truth_and_gives_per_step_curves(tmp_path, backbone):
    source, prepare = held_out_configs(tmp_path, views=(3,))
    run_prepare(prepare, source, backbone, progress=False)
    scene = load_scene(source, "ring")
    clips = held_out_clips(prepare.cache_dir)
    assert len(clips) == 3 and {clip.views for clip in clips} == {3}
    plan = plan_scene(source, prepare, "ring")
    for clip, planned in zip(clips, plan.captured):
        tensors = load_clip(clip)
        captured = torch.stack([scene.load_image(i) for i in planned["images"]])
        assert torch.equal(tensors["frames/gt"], to_uint8(captured))
        assert torch.equal(tensors["frames/ref"], to_uint8(captured[[0, -1]]))
        assert list(clip.refs) == planned["refs"]
        stored, _ = read_safetensors(clip.path, "")
        assert torch.equal(stored["poses"], torch.stack([c.world_to_camera for c in planned["cameras"]]))
    clip_curves = held_out_clip_curves({"E": RestorationPipeline(backbone)}, prepare.cache_dir, progress=False)
    curves = view_averaged_curves(unit_curves(clip_curves))  # Fig. 6 as the report draws it
    assert len(curves["E"]) == backbone.cfg.schedule.deploy_steps and all(map(math.isfinite, curves["E"]))


def test_padded_clips_are_flagged_and_score_each_captured_image_once(tmp_path, backbone):
    source, prepare = held_out_configs(tmp_path, frames_per_clip=9, views=(9,))
    prepare = replace(prepare, held_out_repeat_frames=True)
    run_prepare(prepare, source, backbone, progress=False)
    plan = plan_scene(source, prepare, "ring")
    clips = held_out_clips(prepare.cache_dir)
    assert [clip.captured_images() for clip in clips] == [planned["images"] for planned in plan.captured]
    assert all(clip.padded for clip in clips)  # 40 images, 9 views: fewer than 7 between consecutive views
    # A shard records its clip's captured images: one that does not (made in another capture order, or before
    # the record) is prepared again.
    images = clips[0].captured_images()
    assert shard_is_valid(clips[0].path, images=images) and not shard_is_valid(clips[0].path, images=images[::-1])
    entry = json.loads((Path(prepare.cache_dir) / "manifest.json").read_text())["scenes"]["ring"]
    assert entry["padded_clips"] == list(range(9)) and entry["capture_order"] == NAME_ORDER
    quality = clip_restoration_psnr({}, prepare.cache_dir, progress=False)
    expected, plain = [], []
    for clip in clips:
        tensors = load_clip(clip)
        truth = trajectory_frames(tensors, "gt")
        (condition,) = clip.conditions()
        per_frame = [mean_psnr(f[None], t[None]) for f, t in zip(trajectory_frames(tensors, condition), truth)]
        by_image: dict[int, list[float]] = {}
        for image, value in zip(clip.captured_images()[1:-1], per_frame):
            by_image.setdefault(image, []).append(value)
        expected.append(sum(sum(v) / len(v) for v in by_image.values()) / len(by_image))
        plain.append(sum(per_frame) / len(per_frame))
    assert quality["mean"][INPUT] == pytest.approx(sum(expected) / len(expected))
    assert quality["mean"][INPUT] != pytest.approx(sum(plain) / len(plain))  # repeated frames counted once
