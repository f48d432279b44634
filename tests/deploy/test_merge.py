"""Sharding of evaluation units and merging shards into results.json (scene means, then over scenes)."""

import json

import pytest

from tracegs.deploy.scenes import evaluation_units
from tracegs.eval.merge import merge_results, unit_path
from tracegs.io import write_json_atomic


def _unit(scene, views, base):
    methods = {}
    for i, m in enumerate(("3dgs", "baseline", "tracegs")):
        per_view = [{"psnr": base + i + d, "ssim": 0.5, "lpips": None} for d in (0.0, 2.0)]
        methods[m] = {"per_view": per_view, "mean": {"psnr": base + i + 1.0, "ssim": 0.5, "lpips": None}}
    return {"scene": scene, "views": views,
            "lpips": "LPIPS n/a: VGG16 ImageNet weights not found at /hub/vgg16-397923af.pth",
            "methods": methods, "per_step": {"baseline": [1.0, 2.0], "tracegs": [1.0, 3.0]}}


def test_shards_partition_the_units():
    scenes, views = ["a", "b"], [3, 6, 9]
    shards = [evaluation_units(scenes, views, i, 4) for i in range(4)]
    flat = sorted(u for s in shards for u in s)
    assert flat == sorted((s, k) for s in scenes for k in views)
    assert max(len(s) for s in shards) - min(len(s) for s in shards) <= 1
    with pytest.raises(ValueError, match="shard_index"):
        evaluation_units(scenes, views, 4, 4)


def test_merge_averages_scene_means_and_writes_the_layout(tmp_path):
    for scene, base in (("a", 10.0), ("b", 20.0)):
        for k in (3, 6, 9):
            write_json_atomic(_unit(scene, k, base + k), unit_path(tmp_path, scene, k))
    results = merge_results(tmp_path)
    on_disk = json.loads((tmp_path / "results.json").read_text())
    assert on_disk == json.loads(json.dumps(results))
    for i, method in enumerate(("3dgs", "baseline", "tracegs")):
        for k in ("3", "6", "9"):
            cell = on_disk[method][k]
            assert set(cell) == {"psnr", "ssim", "lpips"}
            # scene means are base + k + i + 1; the two scenes' bases differ by 10
            assert cell["psnr"] == pytest.approx(15.0 + int(k) + i + 1.0)
            assert cell["lpips"] is None
    assert on_disk["meta"]["scenes"] == ["a", "b"]
    assert "VGG16 ImageNet weights not found" in on_disk["meta"]["lpips"]
    assert (tmp_path / "table.md").is_file() and (tmp_path / "table.csv").is_file()
    assert json.loads((tmp_path / "per_step.json").read_text())["tracegs"] == [1.0, 3.0]
    assert (tmp_path / "fig6_per_step.png").is_file()


def test_merge_refuses_incomplete_shards(tmp_path):
    write_json_atomic(_unit("a", 3, 10.0), unit_path(tmp_path, "a", 3))
    with pytest.raises(FileNotFoundError, match="a/views_6"):
        merge_results(tmp_path, scenes=["a"], views=[3, 6])
    with pytest.raises(FileNotFoundError, match="no evaluation units"):
        merge_results(tmp_path / "empty")
