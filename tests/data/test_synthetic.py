"""The synthetic benchmark: deterministic by seed, readable by the COLMAP loader, ground truth at any pose."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose

from tracegs.config.validate import ConfigError, validate
from tracegs.data.colmap import load_scene
from tracegs.data.config import SyntheticConfig
from tracegs.data.synthetic import (
    BACKDROP_TEXTURES,
    GROUND_TEXTURES,
    TEXTURES,
    draw_surroundings,
    generate_benchmark,
    generate_scene,
    render_ground_truth,
)


def test_scene_loads_through_colmap_and_ground_truth_matches_its_images(prepared):
    _, synthetic, source, _, _ = prepared
    scene = load_scene(source, "scene_000")  # normalised frame: ground truth must follow the cameras
    assert len(scene) == synthetic.num_views and scene.caption
    assert scene.cameras[0].height == synthetic.height and scene.cameras[0].width == synthetic.width
    rendered = render_ground_truth(scene, scene.cameras[:3])
    stored = torch.stack([scene.load_image(i) for i in range(3)])
    assert (rendered - stored).abs().max() < 2.5 / 255  # only 8-bit quantisation apart
    # SfM-like tracks: every point is seen by two or more views, and occlusion / frustum hide it from others.
    seen = scene.visibility.sum(dim=1)
    assert len(seen) == synthetic.init_points and (seen >= 2).all() and (seen < len(scene)).float().mean() > 0.5


def test_same_seed_same_scene_different_seed_different_scene(prepared, tmp_path):
    _, synthetic, _, _, _ = prepared
    original = Path(synthetic.root) / "scene_000"
    again = generate_scene(0, synthetic, tmp_path / "again")
    for name in ("images/frame_00000.png", "images/frame_00007.png", "caption.txt"):
        assert (again / name).read_bytes() == (original / name).read_bytes()
    other = generate_scene(5, synthetic, tmp_path / "other")
    assert (other / "images/frame_00000.png").read_bytes() != (original / "images/frame_00000.png").read_bytes()


@pytest.mark.parametrize("seeds", [dict(train_seeds=[0, 1], test_seeds=[1]), dict(train_seeds=[0, 1], val_seeds=[1]),
                                   dict(val_seeds=[1], test_seeds=[1])])
def test_train_val_and_test_seeds_must_be_disjoint(tmp_path, seeds):
    from tracegs.data.config import SyntheticConfig

    cfg = replace(SyntheticConfig(root=str(tmp_path)), **seeds)
    with pytest.raises(ValueError, match="overlap: \\[1\\]"):
        generate_benchmark(cfg, progress=False)
    assert not any(tmp_path.iterdir())


def test_the_default_training_scenes_show_every_ground_and_backdrop():
    """A restorer never shown a backdrop fails on it (a test scene with an unseen backdrop is out of
    distribution, not a measurement of restoration), so the default training seeds cover every ground and
    backdrop texture a validation or test scene can have."""
    seeds = SyntheticConfig().train_seeds
    grounds, backdrops = zip(*(draw_surroundings(np.random.default_rng(seed)) for seed in seeds))
    assert set(grounds) == set(GROUND_TEXTURES) and set(backdrops) == set(BACKDROP_TEXTURES)


def test_the_first_draws_of_a_scene_seed_are_the_textures_it_is_built_with(prepared):
    _, synthetic, _, _, _ = prepared
    ground, backdrop = draw_surroundings(np.random.default_rng(0))
    caption = (Path(synthetic.root) / "scene_000" / "caption.txt").read_text()
    assert f"on {ground} " in caption and caption.rstrip().endswith(backdrop.replace("_", " "))


def test_pretraining_scenes_of_other_textures_are_made_anew_and_the_others_keep_theirs(tmp_path):
    """``pretrain_textures`` gives A's scenes other statistics than the benchmark's: every surface of a pretraining
    scene is one of those photographs, a training scene keeps its own, and a folder made under another palette
    is never reused."""
    other = ["checkerboard", "retina"]
    base = SyntheticConfig(root=str(tmp_path), train_seeds=[0], test_seeds=[], val_seeds=[], pretrain_seeds=[300],
                           num_views=2, height=12, width=16, num_objects=2, gaussians_per_unit_area=20.0,
                           init_points=50)
    plain = (generate_scene(300, base, tmp_path) / "caption.txt").read_text()
    shifted = replace(base, pretrain_textures=other)
    caption = (generate_scene(300, shifted, tmp_path) / "caption.txt").read_text()
    assert caption != plain
    named = [name for name in TEXTURES if f"{name} " in caption or caption.rstrip().endswith(name.replace("_", " "))]
    assert set(named) <= set(other), caption
    assert json.loads((tmp_path / "scene_300" / "scene.json").read_text())["textures"] == other
    training = (generate_scene(0, shifted, tmp_path) / "caption.txt").read_text()
    assert training == (generate_scene(0, base, tmp_path, force=True) / "caption.txt").read_text()
    assert (generate_scene(300, base, tmp_path) / "caption.txt").read_text() == plain


def test_an_unknown_pretraining_texture_is_refused_naming_the_field(hydra_context):
    with pytest.raises(ConfigError, match=r"data\.synthetic\.pretrain_textures.*'marble'"):
        validate(compose(config_name="prepare", overrides=["data.prepare.split=pretrain",
                                                          "data.synthetic.pretrain_textures=[grass,marble]"]))
