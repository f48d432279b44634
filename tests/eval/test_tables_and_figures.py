"""Reports: Tables 1/2 and 3 in every format, grid PNG, comparison video and the Fig. 6 plot."""

import csv
import json

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from tracegs.eval.metrics import ssim_label
from tracegs.eval.tables_and_figures import (
    image_array,
    plot_per_step_quality,
    results_table_markdown,
    save_comparison_video,
    save_qualitative_grid,
    write_ablation_report,
    write_results_tables,
)


def _results(offset: float = 0.0, lpips=None):
    return {
        method: {v: {"psnr": 10.0 + i + int(v) + offset, "ssim": 0.1 * (i + 1), "lpips": lpips,
                     "ssim_alt": 0.1 * (i + 1) + 0.05}
                 for v in ("3", "6", "9")}
        for i, method in enumerate(("3dgs", "baseline", "tracegs"))
    } | {"meta": {"lpips": "LPIPS n/a: VGG16 ImageNet weights not found at /hub/vgg16-397923af.pth",
                  "ssim": ssim_label("gsfixer"), "scenes": ["s0", "s1"]}}


def test_results_table_has_a_column_per_evaluated_view_count():
    results = {method: {v: row for v, row in by_views.items() if v != "6"} if method != "meta" else by_views
               for method, by_views in _results().items()}
    header = results_table_markdown(results).splitlines()[0]
    assert "PSNR↑ 3" in header and "PSNR↑ 9" in header and "6" not in header


def test_results_table_layout_and_formats(tmp_path):
    results = _results()
    md = results_table_markdown(results)
    lines = md.splitlines()
    assert lines[0].split("|")[2].strip() == "PSNR↑ 3" and "LPIPS↓ 9" in lines[0]
    assert [line.split("|")[1].strip() for line in lines[2:5]] == ["3DGS", "Baseline (A)", "TRACE-GS"]
    assert "| TRACE-GS | 15.00 | 18.00 | 21.00 | 0.300 | 0.300 | 0.300 | n/a | n/a | n/a |" in md
    assert "LPIPS n/a: VGG16 ImageNet weights not found" in md and "2 scene(s)" in md
    # The second SSIM column comes last, named in the footnote as LPIPS's convention is.
    assert lines[0].split("|")[-2].strip() == "SSIM′↑ 9" and "SSIM: SSIM of 8-bit PNG images" in md

    paths = write_results_tables(results, tmp_path, stem="table1")
    rows = list(csv.DictReader(paths["csv"].open()))
    assert len(rows) == 9
    row = next(r for r in rows if r["method"] == "baseline" and r["views"] == "6")
    assert float(row["psnr"]) == pytest.approx(17.0) and row["lpips"] == ""
    assert row["lpips_convention"].startswith("LPIPS n/a")
    assert float(row["ssim_alt"]) == pytest.approx(0.25) and row["ssim_convention"].startswith("SSIM of 8-bit")
    assert json.loads(paths["json"].read_text())["tracegs"]["9"]["psnr"] == pytest.approx(21.0)


def test_ablation_table_from_sweep_result_files(tmp_path):
    for variant, offset in (("A", 0.0), ("E", 1.0), ("F", 2.0)):
        res = _results(offset, lpips=0.3)
        if variant == "A":  # the frozen baseline restorer is evaluated as method "baseline" only
            res = {"baseline": res["baseline"], "meta": res["meta"]}
        else:
            res = {"tracegs": res["tracegs"], "3dgs": res["3dgs"], "meta": res["meta"]}
        res["meta"]["variant"] = variant
        run_dir = tmp_path / "sweep" / f"job_{variant}"
        run_dir.mkdir(parents=True)
        (run_dir / "results.json").write_text(json.dumps(res))
    inputs = [tmp_path / "sweep" / f"job_{v}" for v in ("A", "E", "F")]
    md = write_ablation_report({"synthetic": inputs}, tmp_path)
    rows = {r["variant"]: r for r in csv.DictReader((tmp_path / "table3.csv").open())}
    assert list(rows) == ["A", "E", "F"] and rows["F"]["dataset"] == "synthetic"
    # mean over 3/6/9 views: baseline (i=1) -> 11 + 6 = 17; tracegs (i=2) -> 12 + 6 + offset
    assert float(rows["A"]["psnr"]) == pytest.approx(17.0)
    assert float(rows["F"]["psnr"]) == pytest.approx(20.0)
    assert float(rows["E"]["lpips"]) == pytest.approx(0.3)
    assert "| F | 20.00 | 0.300 | 0.300 |" in md.read_text()
    assert "(Synthetic: 3,6,9)" in md.read_text()
    with pytest.raises(FileNotFoundError, match="job_B"):
        write_ablation_report({"synthetic": [tmp_path / "sweep" / "job_B"]}, tmp_path)


def test_ablation_table_has_a_column_group_per_dataset(tmp_path):
    """Paper Table 3: DL3DV and Mip-NeRF 360 side by side, each cell averaged over 3/6/9 views."""
    inputs = {}
    for dataset, shift in (("dl3dv", 0.0), ("mipnerf360", -1.5)):
        for variant in ("A", "F"):
            res = _results(shift + (1.0 if variant == "F" else 0.0), lpips=0.3)
            method = "baseline" if variant == "A" else "tracegs"
            res = {method: res[method], "meta": {**res["meta"], "variant": variant}}
            folder = tmp_path / dataset / variant
            folder.mkdir(parents=True)
            (folder / "results.json").write_text(json.dumps(res))
            inputs.setdefault(dataset, []).append(folder)
    text = write_ablation_report(inputs, tmp_path / "report").read_text()
    header = [cell.strip() for cell in text.splitlines()[0].split("|")[1:-1]]
    assert header == ["Variant", "DL3DV PSNR↑", "DL3DV SSIM↑", "DL3DV LPIPS↓", "Mip-NeRF 360 PSNR↑",
                      "Mip-NeRF 360 SSIM↑", "Mip-NeRF 360 LPIPS↓"]
    # A: baseline 11 + 6 (mean over 3/6/9) + shift; F: tracegs 12 + 6 + 1 + shift.
    assert "| A | 17.00 | 0.200 | 0.300 | 15.50 | 0.200 | 0.300 |" in text
    assert "| F | 19.00 | 0.300 | 0.300 | 17.50 | 0.300 | 0.300 |" in text
    assert "(DL3DV: 3,6,9; Mip-NeRF 360: 3,6,9)" in text
    rows = list(csv.DictReader((tmp_path / "report" / "table3.csv").open()))
    assert [(r["variant"], r["dataset"]) for r in rows] == [("A", "dl3dv"), ("A", "mipnerf360"), ("F", "dl3dv"),
                                                            ("F", "mipnerf360")]


def test_grid_video_and_plot_are_written(tmp_path):
    g = torch.Generator().manual_seed(0)
    frames = {name: torch.rand(5, 3, 24, 36, generator=g) for name in ("3DGS", "Baseline", "TRACE-GS", "GT")}
    grid = save_qualitative_grid({k: list(v[:2]) for k, v in frames.items()}, tmp_path / "grid.png",
                                 min_cell_height=48)
    image = iio.imread(grid)
    # label strip on top, then 2 rows of 4 cells upscaled x2
    assert image.shape[1] == 4 * 72 and image.shape[0] == 28 + 2 * 48
    assert np.array_equal(image[28:28 + 48:2, 72 * 3:72 * 4:2], image_array(frames["GT"][0]))

    video = save_comparison_video(frames, tmp_path / "traj", min_cell_height=48)
    assert video.suffix in (".mp4", ".gif") and video.stat().st_size > 0
    assert iio.imread(video, index=None).shape[0] == 5

    with pytest.raises(ValueError, match="same non-zero number"):
        save_comparison_video({"a": frames["GT"], "b": frames["GT"][:3]}, tmp_path / "bad")

    plot = plot_per_step_quality({"on-policy (F)": [10.0, 12.0, 14.0], "off-policy (E)": [10.0, 11.5, 12.0]},
                                 tmp_path / "fig6.png")
    assert iio.imread(plot).ndim == 3
