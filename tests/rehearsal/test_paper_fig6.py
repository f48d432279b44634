"""Fig. 6 at paper scale, rehearsed: held-out Mip-NeRF 360 clips with per-frame ground truth (captured cameras
between consecutive sparse views, tracegs/data/held_out.py) and the per-step report on them, averaged across
the view settings K = 3, 6, 9."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from paper_scenes import synthetic_scenes, write_mipnerf360
from support.rehearsal import BUDGET, fresh_root, rehearsal_config, rehearsal_run_dir, run_rehearsal_task

from tracegs.data.colmap import load_scene
from tracegs.data.config import SceneSourceConfig
from tracegs.data.images import read_rgb, resize, to_uint8
from tracegs.eval.clips import held_out_clips, load_clip
from tracegs.pipeline.prepare import prepare
from tracegs.pipeline.report import report
from tracegs.pipeline.train import train

# The held-out cache Fig. 6 needs: the student conditions R_s of K = 3, 6, 9 and the captured ground truth
# (no dense fits, no restorer pseudo-targets: the per-step report reads neither).
FIG6_PREPARE = ("data.prepare.split=test", "data.prepare.dense_views=[]", "data.prepare.pseudo_target=gt",
                "data.prepare.student_final_fits=false")


@pytest.mark.slow
def test_fig6_per_step_report_on_held_out_mipnerf360_clips(tmp_path, paper_data, rehearsal_root, vggt_double):
    root = fresh_root(tmp_path, rehearsal_root, paper_data)
    # A Mip-NeRF 360 capture long enough for 9-frame clips between its 9 sparse views (a walk of 96 images),
    # photographed at twice experiment=rehearsal's frame size, so the dataset resizes its images.
    height, width = 32, 48
    _, (generated,) = synthetic_scenes(tmp_path / "generated", [], [100], 2 * height, 2 * width, num_views=96)
    mipnerf360 = write_mipnerf360(tmp_path, [generated], split_files=True)
    scene = generated.name
    held_out = ("data=mipnerf360", f"data.source.root={mipnerf360}", f"data.source.scenes=[{scene}]", *FIG6_PREPARE)
    run_rehearsal_task(prepare, root, "prepare", (*BUDGET, *held_out))
    cache = rehearsal_run_dir(root, "prepare", (*BUDGET, *held_out), key="data.prepare.cache_dir")

    clips = held_out_clips(cache)
    assert sorted({clip.views for clip in clips}) == [3, 6, 9]
    assert len(clips) == 3 + 6 + 9  # every reference pair of every K, as deployment chains them
    source = SceneSourceConfig(root=str(mipnerf360), preset="mipnerf360", height=height, width=width)
    captured = load_scene(source, scene)
    scene_info = json.loads((cache / scene / "scene.json").read_text())
    sparse = {views: set(scene_info["split"]["view_sets"][str(views)]) for views in (3, 6, 9)}
    for clip in clips:
        poses = load_clip(clip)["poses"]
        images = [min(range(len(captured)), key=lambda i: float((captured.cameras[i].world_to_camera - pose).abs()
                                                                 .max())) for pose in poses]
        assert [images[0], images[-1]] == list(clip.refs) and not set(images[1:-1]) & sparse[clip.views]
    # A ground-truth frame is the captured photograph, resized to the dataset's frame size.
    clip = clips[-1]
    tensors = load_clip(clip)
    interior = min(range(len(captured)), key=lambda i: float((captured.cameras[i].world_to_camera
                                                              - tensors["poses"][4]).abs().max()))
    photograph = resize(read_rgb(captured.image_paths[interior]), width, height)
    assert torch.equal(tensors["frames/gt"][4], to_uint8(torch.from_numpy(photograph).permute(2, 0, 1)))

    # Fig. 6 compares A (GSFixer, loaded) and the on-policy student F, trained on DL3DV as the pipeline does.
    run_rehearsal_task(prepare, root, "prepare", BUDGET)
    run_rehearsal_task(train, root, "train", ("stage=stage1", *BUDGET))
    run_rehearsal_task(train, root, "train", ("stage=stage2", "ablation=F", *BUDGET))
    out = tmp_path / "fig6"
    figure = run_rehearsal_task(report, root, "report", (*BUDGET, "report.kind=per_step", "report.inputs=[A,F]",
                                                         f"evaluation.held_out_cache={cache}",
                                                         f"report.output_dir={out}"))
    assert Path(figure).is_file()
    curves = json.loads((out / "per_step_variants.json").read_text())
    assert list(curves) == ["A", "F"]
    steps = rehearsal_config(root, "report").backbone.schedule.deploy_steps
    for curve in curves.values():
        assert len(curve) == steps and all(math.isfinite(value) for value in curve)  # one point per reverse step
    units = (out / "per_step_variants_per_scene.csv").read_text().splitlines()[1:]
    assert {line.split(",")[1] for line in units} == {"3", "6", "9"}  # averaged across the view settings
