import json

import pytest
from scene_builders import write_scene

from tracegs.data.colmap import load_scene
from tracegs.data.config import PrepareConfig, SceneSourceConfig
from tracegs.data.preparation.plan import plan_scene
from tracegs.data.splits import SplitError, make_split, split_scene
from tracegs.deploy.scenes import load_unit
from tracegs.errors import ConfigError


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


# A Mip-NeRF 360 scene folder as ReconFusion's split files complete it (GSFixer's release reads them from the scene
# folder, datasets/colmap_debug.py l. 402-414): {"train_ids": [...], "test_ids": [...]} per K, indexing the
# images sorted by name. Nothing published makes the 3-, 6- and 9-view sets nested, so these are not: the 6- and
# 9-view sets leave out views of the 3-view set.
PUBLISHED_TEST = [0, 8, 16, 24]  # every 8th image, as the 25 test views of bicycle's 194 images
PUBLISHED = {3: [27, 2, 12], 6: [3, 7, 13, 19, 26, 30], 9: [1, 5, 10, 14, 18, 21, 25, 29, 31]}


def published_scene(root):
    """A 32-image scene in the Mip-NeRF 360 layout (images_4, sparse/0) with ReconFusion's split files."""
    root, _ = write_scene(root, n=32, image_dir="images_4")
    for count, ids in PUBLISHED.items():
        (root / f"train_test_split_{count}.json").write_text(json.dumps({"train_ids": ids, "test_ids": PUBLISHED_TEST}))
    return root


@pytest.mark.parametrize("view_rule", ["linspace", "nested"])  # data=mipnerf360's rule, and data=dl3dv's
def test_published_split_files_are_evaluated_as_published(tmp_path, view_rule):
    """Evaluating a K-view set needs that set and the test views, nested in the scene's other sets or not."""
    root = published_scene(tmp_path / "mipnerf360" / "bicycle")
    source = SceneSourceConfig(root=str(root.parent), preset="mipnerf360", view_rule=view_rule)
    scene = load_scene(source, "bicycle")
    split = split_scene(scene, source, [3, 6, 9])
    assert split.test == PUBLISHED_TEST and {k: split.views(k) for k in PUBLISHED} == {
        k: sorted(ids) for k, ids in PUBLISHED.items()}
    for k, ids in PUBLISHED.items():
        unit = load_unit(scene, k, source)
        assert (unit.captured_ids, unit.test_ids) == (sorted(ids), PUBLISHED_TEST)
    # A held-out cache (prepare's test split) is scored as evaluation scores: on the published sets.
    held_out = PrepareConfig(split="test", student_views=[3, 6, 9], dense_views=[12, None], frames_per_clip=3)
    plan = plan_scene(source, held_out, "bicycle")
    assert {k: plan.split.views(k) for k in PUBLISHED} == {k: sorted(ids) for k, ids in PUBLISHED.items()}


def test_training_clips_refuse_published_sets_outside_a_dense_set(tmp_path):
    """Training clips need V_s inside V_d (paper Sec. 3): the 12-view set grows the 9-view file's set, which
    leaves out views of the 3-view file's. With all training views as the only dense set, every V_s is inside."""
    published_scene(tmp_path / "scenes" / "bicycle")
    source = SceneSourceConfig(root=str(tmp_path / "scenes"), preset="mipnerf360")
    training = PrepareConfig(student_views=[3, 6, 9], dense_views=[12, 18, None])
    with pytest.raises(SplitError) as refused:
        plan_scene(source, training, "bicycle")
    (line,) = str(refused.value).splitlines()
    assert line.startswith(f"{tmp_path / 'scenes' / 'bicycle' / 'train_test_split_3.json'}: views [2, 27] of "
                           "the 3-view set are not in the 12-view set"), line
    assert "data.prepare.dense_views=[null]" in line
    plan = plan_scene(source, PrepareConfig(student_views=[3, 6, 9], dense_views=[None], pseudo_target="dense"),
                      "bicycle")
    assert plan.split.views(3) == sorted(PUBLISHED[3])


def test_training_clips_refuse_the_linspace_rule(tmp_path):
    """GSFixer's rule picks each set on its own: no split file to blame, so the config field is named."""
    write_scene(tmp_path / "scenes" / "ring", n=32)
    source = SceneSourceConfig(root=str(tmp_path / "scenes"), preset="custom", view_rule="linspace")
    with pytest.raises(ConfigError, match=r"^config field 'data.source.view_rule': linspace picks each view set on "
                                          r"its own, and scene ring's 3-view set .* use nested$"):
        plan_scene(source, PrepareConfig(student_views=[3], dense_views=[12, None]), "ring")


def test_split_files_with_different_test_views_are_refused_in_one_line(tmp_path):
    (tmp_path / "train_test_split_3.json").write_text(json.dumps({"train_ids": [1, 2, 3], "test_ids": [0, 8]}))
    (tmp_path / "train_test_split_6.json").write_text(json.dumps({"train_ids": [1, 2, 3, 4, 5, 6], "test_ids": [0]}))
    with pytest.raises(SplitError) as refused:
        make_split(12, [3, 6], split_dir=tmp_path)
    assert str(refused.value) == (f"{tmp_path / 'train_test_split_6.json'}: test_ids differ from "
                                  "train_test_split_3.json's; one test set serves every view set of a scene, so "
                                  "give the scene's split files the same test_ids")


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
