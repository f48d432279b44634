"""The paper's datasets in their on-disk layouts, read by the production scene loaders."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from support.rehearsal import rehearsal_config

from tracegs.data import colmap
from tracegs.data.colmap import SceneFormatError, list_scenes, load_scene
from tracegs.data.config import SceneSourceConfig, SyntheticConfig
from tracegs.data.preparation.plan import plan_scene
from tracegs.data.splits import make_split
from tracegs.data.synthetic import camera_path


def source(root: Path, preset: str, **fields) -> SceneSourceConfig:
    return SceneSourceConfig(root=str(root), preset=preset, height=32, width=48, **fields)


def test_dl3dv_reads_training_and_benchmark_scenes_from_their_lists(rehearsal_root, paper_data):
    cfg = OmegaConf.to_object(rehearsal_config(rehearsal_root, "evaluate").data.source)
    assert Path(cfg.root) == paper_data["dl3dv"]
    assert list_scenes(cfg, "train") == ["scene_000"]
    assert list_scenes(cfg, "test") == ["scene_100"]


def test_a_benchmark_list_naming_a_training_scene_is_refused(paper_data, tmp_path):
    listed = tmp_path / "benchmark.txt"
    listed.write_text("scene_100\nscene_000\n")
    cfg = source(paper_data["dl3dv"], "dl3dv", train_list=str(paper_data["dl3dv"] / "train_scenes.txt"),
                 test_list=str(listed))
    with pytest.raises(SceneFormatError, match="training scenes \\['scene_000'\\]"):
        list_scenes(cfg, "test")


def test_downscaled_images_get_rescaled_full_resolution_intrinsics(paper_data):
    scene = load_scene(source(paper_data["dl3dv"], "dl3dv", normalize=False), "scene_100")
    generated = camera_path(SyntheticConfig(num_views=24, height=32, width=48), "orbit", 100)
    assert torch.allclose(scene.cameras[0].K, generated[0].K, atol=1e-4)
    assert scene.load_image(0).shape == (3, 32, 48)


@pytest.mark.parametrize("with_splits", [True, False])
def test_mipnerf360_view_sets_follow_reconfusion_files_when_present(paper_data, with_splits):
    root = paper_data["mipnerf360" if with_splits else "mipnerf360_no_splits"]
    prepare = OmegaConf.to_object(rehearsal_config(root.parent, "prepare").data.prepare)
    scene_root = root / "scene_100"
    plan = plan_scene(source(root, "mipnerf360"), prepare, "scene_100")
    if with_splits:
        stored = json.loads((scene_root / "train_test_split_3.json").read_text())
        assert plan.split.views(3) == stored["train_ids"] and plan.split.test == stored["test_ids"]
        assert plan.split.views(3) != make_split(24, [3]).views(3)  # not what the fallback rule picks
    else:
        assert plan.split.test == list(range(0, 24, 8))
    assert set(plan.split.views(3)) <= set(plan.split.views(6)) <= set(plan.split.views(9))


def test_nerfbusters_evaluates_on_its_second_capture(paper_data):
    cfg = source(paper_data["nerfbusters"], "nerfbusters")
    scene = load_scene(cfg, "scene_100")
    test = colmap.test_indices_for(cfg, scene)
    assert test and all(scene.image_names[i].startswith("frame_2_") for i in test)
    assert len(test) == 3 and len(scene) == 24
