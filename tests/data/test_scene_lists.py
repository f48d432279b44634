"""Benchmark scene lists ship with the configs, and evaluation refuses a training scene."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from scene_builders import write_scene

from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs
from tracegs.data.colmap import SceneFormatError, list_scenes, read_scene_list
from tracegs.data.config import SceneSourceConfig
from tracegs.pipeline.evaluate import deploy, evaluate

PUBLISHED = {
    "mipnerf360": ["bicycle", "bonsai", "counter", "flowers", "garden", "kitchen", "room", "stump", "treehill"],
    "nerfbusters": ["aloe", "art", "car", "century", "flowers", "garbage", "picnic", "pikachu", "pipe", "plant",
                    "roses", "table"],
}


@pytest.mark.parametrize("data", sorted(PUBLISHED))
def test_published_benchmark_lists_are_found_from_the_config(data, tmp_path):
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=["experiment=paper", f"data={data}"])
    assert read_scene_list(cfg.data.source.test_list, "source.test_list") == PUBLISHED[data]
    # The list is read whatever the working directory, and its scenes must exist under the root.
    source = SceneSourceConfig(root=str(tmp_path), preset=data, test_list=cfg.data.source.test_list)
    with pytest.raises(SceneFormatError, match="not under"):
        list_scenes(source, "test")


@pytest.mark.parametrize("stage", ["evaluate", "deploy"])
def test_evaluating_a_training_scene_is_refused_before_any_work(stage, tmp_path):
    write_scene(tmp_path / "scenes" / "ring")
    (tmp_path / "train.txt").write_text("ring\n")
    out = tmp_path / "out"
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name=stage, overrides=[
            "data=custom", f"data.source.root={tmp_path / 'scenes'}", f"data.source.train_list={tmp_path}/train.txt",
            "evaluation.scenes=[ring]", "evaluation.methods=[3dgs]", f"evaluation.out_dir={out}", f"run_dir={out}"])
    with pytest.raises(SceneFormatError, match=r"training scenes \['ring'\]"):
        (evaluate if stage == "evaluate" else deploy)(cfg)
    assert not out.exists()


TRAINING_ON_A_BENCHMARK = {
    # Mip-NeRF 360 with no training list (the README's `tracegs-prepare data=mipnerf360`): every folder.
    "mipnerf360_every_folder": ("mipnerf360", "garden", [], "null, so every scene under "),
    "nerfbusters_named": ("nerfbusters", "pikachu", ["data.source.scenes=[pikachu]"],
                          "scene 'pikachu' is a NeRFBusters benchmark scene"),
    # DL3DV: the benchmark scenes are the user's benchmark_scenes.txt.
    "dl3dv_without_a_training_list": ("dl3dv", "0a1b2c", ["data.source.train_list=null"], "null, so every scene"),
    "dl3dv_benchmark_scene_listed": ("dl3dv", "0a1b2c", ["data.source.scenes=[0a1b2c]"],
                                     "scene '0a1b2c' is on source.test_list="),
}


@pytest.mark.parametrize("case", sorted(TRAINING_ON_A_BENCHMARK))
def test_preparing_training_data_from_benchmark_scenes_is_refused_before_any_work(entry_point, tmp_path, case):
    data, scene, extra, named = TRAINING_ON_A_BENCHMARK[case]
    root = tmp_path / "data"
    write_scene(root / scene)
    (root / "benchmark_scenes.txt").write_text(f"{scene}\n")
    out = tmp_path / "out"
    result = entry_point("prepare", ["experiment=rehearsal", f"data={data}", f"data.source.root={root}",
                                     f"paths.root_dir={out}", *extra], tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    (line,) = result.stderr_lines()
    assert line.startswith(f"tracegs-prepare: error: config field 'data.source.train_list': {named}"), line
    assert not out.exists()  # refused before Hydra's run folder, a model or a scene was touched


TRAINING_STAGE2_ON_A_BENCHMARK = {
    # The experiment trains on DL3DV: another dataset is evaluated, never trained on.
    "not_the_training_data": ([], "config field 'training_data': 'dl3dv', but this run trains on data=mipnerf360"),
    # Named as the training data, a benchmark-only dataset with no training list: all its scenes are benchmarks.
    "named_training_data": (["training_data=mipnerf360"], "config field 'data.source.train_list': null, so every"),
}


@pytest.mark.parametrize("case", sorted(TRAINING_STAGE2_ON_A_BENCHMARK))
def test_training_stage2_on_a_benchmark_is_refused_before_any_work(entry_point, tmp_path, case):
    extra, named = TRAINING_STAGE2_ON_A_BENCHMARK[case]
    out = tmp_path / "out"
    result = entry_point("train", ["experiment=rehearsal", "data=mipnerf360", "stage=stage2",
                                   f"paths.root_dir={out}", *extra], tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    (line,) = result.stderr_lines()
    assert line.startswith(f"tracegs-train: error: {named}"), line
    assert not out.exists()
