"""Benchmark scene lists ship with the configs, and evaluation refuses a training scene."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from scene_builders import write_scene

from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs
from tracegs.data.colmap import SceneFormatError, list_scenes, read_scene_list
from tracegs.data.config import SceneSourceConfig
from tracegs.errors import InputFileError
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


# DL3DV-Benchmark publishes its scenes as benchmark-meta.csv: a header row, then a row a scene whose "hash" column
# names its folder (a 64-hex hash, as GSFixer's DL3DV scripts list the scene folders). The other columns are labels
# this reader ignores; their names here are placeholders.
DL3DV_HASHES = ["9f518d266943220090b58a2fc950772767a6eba1162fb49ff721cbdabeba3b95",
                "0a1b2c3d4e5f60718293a4b5c6d7e8f90a1b2c3d4e5f60718293a4b5c6d7e8f9"]


def test_dl3dv_benchmark_list_loads_as_published(tmp_path):
    root = tmp_path / "DL3DV-10K"
    for name in DL3DV_HASHES:
        write_scene(root / name, image_dir="images_4")
    table = root / "benchmark-meta.csv"
    table.write_text("\ufeff" + "label_a,hash,label_b\n" + "".join(f"x,{h},y\n" for h in DL3DV_HASHES),
                     encoding="utf-8")
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=["experiment=paper", "data=dl3dv", f"data.source.root={root}",
                                                         f"data.source.test_list={table}",
                                                         "data.source.train_list=null"])
    assert list_scenes(OmegaConf.to_object(cfg.data.source), "test") == DL3DV_HASHES
    # A scene on both lists is still refused: evaluation never runs on a scene the restorer was trained on.
    (root / "train_scenes.txt").write_text(f"{DL3DV_HASHES[1]}\n")
    source = SceneSourceConfig(root=str(root), preset="dl3dv", test_list=str(table),
                               train_list=str(root / "train_scenes.txt"))
    with pytest.raises(SceneFormatError, match=f"training scenes \\['{DL3DV_HASHES[1]}'\\]"):
        list_scenes(source, "test")


def test_a_scene_table_without_a_hash_column_is_refused_in_one_line(tmp_path):
    table = tmp_path / "benchmark-meta.csv"
    table.write_text("scene,batch\nkitchen,1K\n")
    with pytest.raises(InputFileError) as refused:
        read_scene_list(str(table), "source.test_list")
    assert str(refused.value) == (f"{table}: no 'hash' column in its header ['scene', 'batch']; name the scene "
                                  "folders in a 'hash' column, or one a line in a .txt file, for source.test_list")


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
