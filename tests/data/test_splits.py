import json

import pytest

from tracegs.data.splits import SplitError, make_split


def test_every_eighth_is_held_out_and_view_sets_are_nested_and_spread():
    split = make_split(32, [3, 6, 9, 12, 18, None])
    assert split.test == [0, 8, 16, 24]
    assert set(split.train) == set(range(32)) - {0, 8, 16, 24}
    chain = [split.views(k) for k in (3, 6, 9, 12, 18, None)]
    for small, large in zip(chain, chain[1:]):
        assert set(small) < set(large)
    assert [len(v) for v in chain] == [3, 6, 9, 12, 18, 28]
    assert not set(split.views(None)) & set(split.test)
    # Evenly spread: the three sparse views cover both ends of the training range and its middle.
    three = split.views(3)
    assert three[0] == split.train[0] and three[-1] == split.train[-1]
    assert abs(three[1] - 16) <= 2


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
    with pytest.raises(SplitError, match="asked for 18 training views but the scene has only 14"):
        make_split(16, [3, 18])
