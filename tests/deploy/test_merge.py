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
            # Units scored before the second SSIM column existed leave it empty.
            assert set(cell) == {"psnr", "ssim", "lpips", "ssim_alt"} and cell["ssim_alt"] is None
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


def test_merge_takes_methods_from_other_evaluations_of_the_same_units(tmp_path):
    """Tables 1/2 from an ablation sweep: 3DGS from this evaluation, A's and F's scores and Fig. 6 curves from the
    evaluations of variants A and F (each holding its own method only); a method no folder scored is refused."""
    own, a, f = tmp_path / "main", tmp_path / "A", tmp_path / "F"
    for folder, method, offset in ((own, "3dgs", 0.0), (a, "baseline", 100.0), (f, "tracegs", 200.0)):
        for scene in ("a", "b"):
            unit = _unit(scene, 3, 10.0 + offset)
            unit["methods"] = {method: unit["methods"][method]}
            unit["per_step"] = {m: c for m, c in unit["per_step"].items() if m == method}
            write_json_atomic(unit, unit_path(folder, scene, 3))
    with pytest.raises(FileNotFoundError, match="evaluation.methods: no scores of baseline"):
        merge_results(own, methods=["3dgs", "baseline", "tracegs"])
    results = merge_results(own, methods=["3dgs", "baseline", "tracegs"], sources={"baseline": a, "tracegs": f})
    assert [results[m]["3"]["psnr"] for m in ("3dgs", "baseline", "tracegs")] == pytest.approx([11.0, 112.0, 213.0])
    assert results["meta"]["methods_from"] == {"baseline": "../A", "tracegs": "../F"}
    assert json.loads((own / "per_step.json").read_text()) == {"baseline": [1.0, 2.0], "tracegs": [1.0, 3.0]}
    assert not (a / "results.json").exists() and not (f / "results.json").exists()  # the sweep's folders untouched
