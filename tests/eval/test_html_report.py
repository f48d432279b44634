"""``report.html`` of an evaluation folder made by the real merge (tables, intervals with verdicts, Fig. 6): the
project's markdown as HTML tables, the verdicts marked, the plot linked relatively, the same bytes when made again;
a demo's combined tables.md stands for its parts."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from support.report_page import checked_page

from tracegs.eval.html_report import markdown_html, report_html, write_report_page
from tracegs.eval.merge import merge_results, unit_path
from tracegs.io import write_json_atomic

SCENES = [f"scene_{100 + i}" for i in range(6)]


def evaluation_folder(folder: Path) -> Path:
    """Six scenes on which TRACE-GS beats A by 0.4 dB everywhere (a verdict that holds), merged into tables."""
    for index, scene in enumerate(SCENES):
        psnr = {"3dgs": 15.0 + index, "baseline": 15.2 + index, "tracegs": 15.6 + index}
        methods = {m: {"per_view": [{"psnr": v, "ssim": 0.5, "lpips": None}],
                       "mean": {"psnr": v, "ssim": 0.5, "lpips": None}} for m, v in psnr.items()}
        write_json_atomic({"scene": scene, "views": 3, "lpips": "LPIPS n/a", "methods": methods,
                           "per_step": {"baseline": [15.0, 16.0 + index], "tracegs": [15.0, 16.5 + index]}},
                          unit_path(folder, scene, 3))
    merge_results(folder)
    return folder


def test_an_evaluation_page_shows_its_tables_verdicts_and_fig6(tmp_path):
    folder = evaluation_folder(tmp_path / "eval")
    write_report_page(folder)
    text, links = checked_page(folder, "intervals.md")
    checked_page(folder, "table.md")
    assert '<strong class="holds">holds</strong>' in text
    separators = [line for path in folder.glob("*.md") for line in path.read_text().splitlines()
                  if line.startswith("|---")]
    assert text.count("<table>") == len(separators)
    assert set(links) == {"table.md", "intervals.md", "per_step_intervals.md", "fig6_per_step.png"}


def test_a_demo_tables_md_stands_for_the_parts_it_is_made_of(tmp_path):
    folder = evaluation_folder(tmp_path / "demo")
    (folder / "tables.md").write_text("Deployment on the test scenes:\n\n" + (folder / "table.md").read_text())
    text = report_html(folder)
    assert "Deployment on the test scenes:" in text and 'href="intervals.md"' not in text
    assert text.count("<table>") == 1


def test_the_project_markdown_becomes_headings_tables_lists_and_paragraphs():
    page = markdown_html("## Held-out clips\n\nPSNR (dB), `make replicate`:\n\n| a | b |\n|---|---:|\n| 1 < 2 | x |\n\n"
                         "- F > A: **reversed** (-0.1)\n- A > 3DGS: **not resolved**\n")
    assert page.splitlines() == [
        "<h3>Held-out clips</h3>", "<p>PSNR (dB), <code>make replicate</code>:</p>",
        "<table>", "<thead><tr><th>a</th><th>b</th></tr></thead>", "<tbody>", "<tr><td>1 &lt; 2</td><td>x</td></tr>",
        "</tbody>", "</table>",
        "<ul>", '<li>F &gt; A: <strong class="reversed">reversed</strong> (-0.1)</li>',
        "<li>A &gt; 3DGS: <strong>not resolved</strong></li>", "</ul>"]


CHROMIUM = shutil.which("chromium")


@pytest.mark.browser
@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium (make test-browser installs it)")
def test_chromium_shows_the_tables_and_the_plot_from_disk(tmp_path):
    """Headless Chromium opens the page as a file (no server): the DOM it built holds every table and the
    screenshot holds Fig. 6's lines, in matplotlib's first colour, which nothing else on the page is drawn in."""
    folder = evaluation_folder(tmp_path / "eval")
    page = write_report_page(folder)
    browse = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--window-size=1000,4000"]
    dom = subprocess.run([*browse, "--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120,
                         check=True).stdout
    assert dom.count("<table>") == page.read_text().count("<table>") > 0
    assert "+0.40 [+0.40, +0.40]" in dom and 'class="holds"' in dom
    shot = tmp_path / "page.png"
    subprocess.run([*browse, f"--screenshot={shot}", page.as_uri()], capture_output=True, timeout=120, check=True)
    pixels = iio.imread(shot)[..., :3].astype(int)
    plot_blue = (abs(pixels - np.array([31, 119, 180])).sum(axis=-1) < 30).sum()
    assert plot_blue > 200


def test_a_capture_page_is_titled_by_it_names_its_photos_and_says_each_label_once(tmp_path):
    """One capture restored: the page's title is the capture's name, its views are its photos' file names (escaped),
    no interval of one value is shown, and the LPIPS note does not repeat its own name."""
    folder = tmp_path / "seed0-0123abcd"
    methods = {m: {"per_view": [{"psnr": 20.0, "ssim": 0.5, "lpips": None}],
                   "mean": {"psnr": 20.0, "ssim": 0.5, "lpips": None}} for m in ("3dgs", "baseline")}
    write_json_atomic({"scene": "Mes photos d'été", "views": 2, "captured": [0, 2], "test": [1],
                       "names": {"0": "<a>.jpg", "1": "b & c.jpg", "2": "IMG_2.jpg"},
                       "lpips": "LPIPS n/a: VGG16 ImageNet weights not found", "methods": methods,
                       "media": {"grid": "media/grid.png"}},
                      unit_path(folder, "Mes photos d'été", 2))
    merge_results(folder)
    text = report_html(folder)
    assert "<title>Mes photos d&#x27;été: tracegs results</title>" in text and "0123abcd" not in text
    assert "Fitted from &lt;a&gt;.jpg, IMG_2.jpg, scored on held-out b &amp; c.jpg." in text
    assert "[n/a" not in text and "95% intervals" not in text
    assert "LPIPS n/a: VGG16" in text and "LPIPS: LPIPS" not in text
