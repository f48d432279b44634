import json

import pytest
from scene_builders import write_scene

from tracegs.data.colmap import load_scene
from tracegs.data.config import PrepareConfig, SceneSourceConfig
from tracegs.data.prepare import plan_scene
from tracegs.data.splits import SplitError, make_split
from tracegs.deploy.scenes import load_unit


def test_every_eighth_is_held_out_and_view_sets_are_nested_and_spread():
    split = make_split(32, [3, 6, 9, 12, 18, None])
    assert split.test == [0, 8, 16, 24]
    assert set(split.train) == set(range(32)) - {0, 8, 16, 24}
    chain = [split.views(k) for k in (3, 6, 9, 12, 18, None)]
    for small, large in zip(chain, chain[1:]):
        assert set(small) < set(large)
    assert [len(v) for v in chain] == [3, 6, 9, 12, 18, 28]
    assert not set(split.views(None)) & set(split.test)


def test_three_views_of_a_360_capture_are_spread_around_it():
    """Image i of a 32-image ring capture sits at 360 i / 32 degrees: the first and last images are
    neighbours, so a rule that takes both ends leaves a 22.5-degree gap between two of three views."""
    num_images = 32
    three = make_split(num_images, [3]).views(3)
    angles = sorted(360.0 * i / num_images for i in three)
    gaps = [b - a for a, b in zip(angles, angles[1:])] + [360.0 - angles[-1] + angles[0]]
    assert min(gaps) >= 100.0, (three, gaps)
    # The spread holds up the ladder: no two of the 6 views are neighbouring training images.
    six = make_split(num_images, [6]).views(6)
    assert min((b - a) % num_images for a, b in zip(six, six[1:] + six[:1])) >= 3, six


def test_a_view_set_does_not_depend_on_the_other_counts_asked_for():
    alone = {k: make_split(32, [k]).views(k) for k in (3, 6, 9, 12, 18)}
    ladder = make_split(32, [3, 6, 9, 12, 18, None])
    assert alone == {k: ladder.views(k) for k in alone}


def test_prepare_and_evaluation_select_the_same_nested_views(tmp_path):
    root, _ = write_scene(tmp_path / "scenes" / "ring", n=32)
    source = SceneSourceConfig(root=str(root.parent), preset="custom")
    prepare = PrepareConfig(student_views=[3, 6, 9], dense_views=[12, 18, None], pseudo_target="dense")
    plan = plan_scene(source, prepare, "ring")
    scene = load_scene(source, "ring")
    evaluated = {k: load_unit(scene, k, source) for k in (3, 6, 9)}
    for k, unit in evaluated.items():
        assert unit.captured_ids == plan.split.views(k), k
        assert unit.test_ids == plan.split.test
    chain = [evaluated[k].captured_ids for k in (3, 6, 9)] + [plan.split.views(k) for k in (12, 18, None)]
    for small, large in zip(chain, chain[1:]):
        assert set(small) < set(large)


def test_reconfusion_split_json_is_honoured(tmp_path):
    test_ids = [0, 5, 10]
    json_three = [2, 7, 13]
    json_six = [1, 2, 7, 11, 13, 14]
    for count, ids in ((3, json_three), (6, json_six)):
        (tmp_path / f"train_test_split_{count}.json").write_text(json.dumps({"train_ids": ids, "test_ids": test_ids}))
    split = make_split(16, [3, 6, 9, None], split_dir=tmp_path)
    assert split.test == test_ids
    assert split.views(3) == json_three and split.views(6) == json_six
    assert set(json_six) < set(split.views(9)) and not set(split.views(9)) & set(test_ids)
    assert split.views(None) == [i for i in range(16) if i not in test_ids]


def test_split_json_that_breaks_nesting_is_rejected(tmp_path):
    (tmp_path / "train_test_split_3.json").write_text(json.dumps({"train_ids": [1, 2, 3], "test_ids": [0]}))
    (tmp_path / "train_test_split_6.json").write_text(json.dumps({"train_ids": [4, 5, 6, 7, 9, 10],
                                                                  "test_ids": [0]}))
    with pytest.raises(SplitError, match="train_test_split_6.json.*nested"):
        make_split(12, [3, 6], split_dir=tmp_path)


def test_more_views_than_exist_fails_clearly():
    with pytest.raises(SplitError, match="18 training views, but of the scene.s 16 images 2 are held out.*leaving 14"):
        make_split(16, [3, 18])


def test_linspace_rule_picks_gsfixers_sparse_views():
    """GSFixer's release, datasets/colmap_debug.py l. 416-422: test = every 8th image, train = the rest, and the
    K views are ``train[round(i)] for i in np.linspace(0, len(train) - 1, K)`` (both ends, half to even)."""
    split = make_split(30, [3, 6, 9], view_rule="linspace")
    train = [i for i in range(30) if i % 8 != 0]  # 26 views
    assert split.test == [0, 8, 16, 24]
    # linspace(0, 25, 3) = 0, 12.5, 25: 12.5 rounds to 12 (half to even), so train[12] = 14
    assert split.views(3) == [train[0], train[12], train[25]] == [1, 14, 29]
    # linspace(0, 25, 6) = 0, 5, 10, 15, 20, 25
    assert split.views(6) == [train[i] for i in (0, 5, 10, 15, 20, 25)]
    assert split.views(9) == [train[round(i)] for i in (0, 3.125, 6.25, 9.375, 12.5, 15.625, 18.75, 21.875, 25)]
    assert split.views(3) != make_split(30, [3]).views(3)  # not the nested rule's
