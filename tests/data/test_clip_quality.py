"""Held-out clip quality: the input R_s and each restorer scored against ground truth."""

from __future__ import annotations

import shutil

import pytest

from tracegs.data.datamodule import CacheError
from tracegs.data.preparation.shards import read_shard_psnr
from tracegs.eval.clips import (
    INPUT,
    clip_restoration_psnr,
    held_out_clip_curves,
    unit_curves,
    view_averaged_curves,
)
from tracegs.io import read_safetensors, save_safetensors_atomic
from tracegs.restorer.sampler import RestorationPipeline


def test_scores_input_and_restorer_per_condition_reproducibly(prepared, backbone):
    tmp = prepared[0]
    cache = tmp / "cache"
    pipeline = RestorationPipeline(backbone)
    first = clip_restoration_psnr({"untrained": pipeline}, cache, progress=False)
    again = clip_restoration_psnr({"untrained": pipeline}, cache, progress=False)
    assert first == again  # seeded noise: the same restorer scores the same
    assert first["clips"] == 2 and first["scenes"] == ["scene_000"]
    assert set(first["conditions"]) == {"s3_it8"}
    row = first["conditions"]["s3_it8"]
    # The input row is R_s against ground truth, as prepare measured it (up to 8-bit storage).
    shards = sorted((cache / "scene_000").glob("clip_*.safetensors"))
    measured = sum(read_shard_psnr(p)["s3_it8"] for p in shards) / len(shards)
    assert row[INPUT] == pytest.approx(measured, abs=0.2)
    # An untrained restorer produces noise, far from the rendering it was given.
    assert row["untrained"] < row[INPUT] - 3.0
    assert first["mean"] == row


def test_needs_ground_truth_frames_and_names_the_shard(prepared, backbone, tmp_path):
    cache = tmp_path / "cache"
    shutil.copytree(prepared[0] / "cache", cache)
    shard = cache / "scene_000" / "clip_001.safetensors"
    tensors, metadata = read_safetensors(shard, "")
    del tensors["frames/gt"]
    save_safetensors_atomic(tensors, shard, metadata)  # a shard as prepare writes one for a scene without ground truth
    with pytest.raises(CacheError, match="clip_001.safetensors: no ground-truth frames"):
        clip_restoration_psnr({"untrained": RestorationPipeline(backbone)}, cache, progress=False)


def test_per_step_curves_cover_every_reverse_step_for_each_pipeline(prepared, backbone):
    pipeline = RestorationPipeline(backbone)
    # Fig. 6 as the report draws it: each clip's curves, the mean per (scene, K), then the mean over K.
    clip_curves = held_out_clip_curves({"E": pipeline, "F": pipeline}, prepared[0] / "cache", progress=False)
    curves = view_averaged_curves(unit_curves(clip_curves))
    assert list(curves) == ["E", "F"]
    assert len(curves["E"]) == backbone.cfg.schedule.deploy_steps
    assert curves["E"] == curves["F"]  # same clips, conditions and noise for every variant
