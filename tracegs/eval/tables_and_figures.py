"""Reports of the evaluation: Tables 1/2 and 3, qualitative grids, videos and the Fig. 6 plot.

The results layout shared with ``eval/scoring.py`` is
``{method: {views: {"psnr": float, "ssim": float, "lpips": float | None}}}`` with methods such as
``3dgs``/``baseline``/``tracegs`` and view counts as strings (``"3"``, ``"6"``, ``"9"``), plus an
optional ``"meta"`` entry (LPIPS convention, scenes, variant) that every table repeats.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from torch import Tensor

from tracegs.data.images import to_uint8
from tracegs.eval.interval_tables import (
    ablation_intervals_markdown,
    held_out_intervals_markdown,
    write_per_scene_csv,
)
from tracegs.eval.labels import DATASET_LABELS, METHOD_LABELS, METRIC_DECIMALS, METRIC_LABELS
from tracegs.eval.metrics import HEADLINE_METRICS, METRIC_NAMES
from tracegs.io import atomic_directory, atomic_write, write_json_atomic

DEFAULT_METHODS = ("3dgs", "baseline", "tracegs")
META_KEY = "meta"


def _fmt(value: float | None, metric: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return f"{value:.{METRIC_DECIMALS[metric]}f}"


def _labelled(metric: str, label: str) -> str:
    """``label`` after ``metric``'s name, said once: a label that begins with the name already ("LPIPS n/a: ...",
    "LPIPS-VGG ...") stands alone."""
    return label if label.startswith(metric) else f"{metric}: {label}"


def _footnote(results: Mapping) -> str:
    meta = results.get(META_KEY, {})
    lines = [f"SSIM: {meta.get('ssim', 'not recorded')}.", f"{_labelled('LPIPS', meta.get('lpips', 'not recorded'))}."]
    scenes = meta.get("scenes")
    if scenes:
        lines.append(
            f"Each metric is averaged over a scene's test views (reference frames excluded), then over "
            f"{len(scenes)} scene(s): {', '.join(scenes)}."
        )
    return "\n".join(lines)


def methods_in(results: Mapping) -> list[str]:
    """Method keys of a results dict in report order (known methods first)."""
    present = [m for m in results if isinstance(results[m], Mapping) and m != META_KEY]
    return [m for m in DEFAULT_METHODS if m in present] + [m for m in present if m not in DEFAULT_METHODS]


def views_in(results: Mapping) -> list[str]:
    """The view counts any method of a results dict was evaluated at, in increasing order."""
    return sorted({v for m in methods_in(results) for v in results[m]}, key=int)


def results_table_markdown(results: Mapping, views: Sequence[str] | None = None) -> str:
    """Tables 1/2 layout: one row per method, columns PSNR/SSIM/LPIPS x view counts (default: those evaluated)."""
    views = views_in(results) if views is None else views
    header = ["Method"] + [f"{METRIC_LABELS[m]} {v}" for m in METRIC_NAMES for v in views]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for method in methods_in(results):
        cells = [METHOD_LABELS.get(method, method)]
        for metric in METRIC_NAMES:
            cells += [_fmt(results[method].get(v, {}).get(metric), metric) for v in views]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\n" + _footnote(results) + "\n"


def write_results_tables(results: Mapping, out_dir: str | Path, stem: str = "table",
                         views: Sequence[str] | None = None) -> dict[str, Path]:
    """Write ``<stem>.md``, ``<stem>.csv`` (long format, one row per method x views) and ``<stem>.json``."""
    views = views_in(results) if views is None else views
    out_dir = Path(out_dir)
    paths = {ext: out_dir / f"{stem}.{ext}" for ext in ("md", "csv", "json")}
    with atomic_write(paths["md"]) as tmp:
        tmp.write_text(results_table_markdown(results, views))
    lpips_note = results.get(META_KEY, {}).get("lpips", "not recorded")
    ssim_note = results.get(META_KEY, {}).get("ssim", "not recorded")
    with atomic_write(paths["csv"]) as tmp, tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["method", "views", *METRIC_NAMES, "lpips_convention", "ssim_convention"])
        for method in methods_in(results):
            for v in views:
                row = results[method].get(v, {})
                writer.writerow([method, v, *[_csv_value(row.get(m)) for m in METRIC_NAMES], lpips_note, ssim_note])
    write_json_atomic(dict(results), paths["json"])
    return paths


def _csv_value(value: float | None) -> str:
    return "" if value is None else repr(float(value))


# ---------------------------------------------------------------- Table 3 (ablation sweep)


def load_results(path: str | Path) -> dict:
    """Read a ``results.json`` written by ``eval.scoring`` (clear error naming the file)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"results file not found: {path}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON: {err}") from err


def ablation_rows(variant_results: Mapping[str, Mapping], method: str = "tracegs") -> dict[str, dict]:
    """Per variant: each metric averaged over the view counts evaluated (Table 3 averages 3/6/9).

    Variant A is the frozen baseline restorer, evaluated as method ``baseline``; any variant whose
    results lack ``method`` falls back to its only restorer method.
    """
    rows = {}
    for variant, results in variant_results.items():
        chosen = variant_method(variant, results, method)
        per_view = list(results[chosen].values())
        rows[variant] = {
            metric: (None if any(r.get(metric) is None for r in per_view)
                     else float(np.mean([r[metric] for r in per_view])))
            for metric in HEADLINE_METRICS
        }
        rows[variant]["views"] = ",".join(results[chosen].keys())
    return rows


def variant_method(variant: str, results: Mapping, method: str = "tracegs") -> str:
    """The method that stands for ``variant`` in its results: ``method`` if evaluated, else its only restorer."""
    if method in results:
        return method
    candidates = [m for m in methods_in(results) if m != "3dgs"]
    if len(candidates) != 1:
        raise ValueError(f"variant {variant!r}: cannot tell which method to report among {candidates}")
    return candidates[0]


def _views_note(rows: Mapping[str, Mapping]) -> str:
    """The view counts a dataset's cells average: one list, or each variant's where they differ."""
    counts = {row["views"] for row in rows.values()}
    if len(counts) == 1:
        return next(iter(counts))
    return "; ".join(f"{variant}: {row['views']}" for variant, row in rows.items())


def write_ablation_table(dataset_files: Mapping[str, Mapping[str, str | Path]], out_dir: str | Path,
                         stem: str = "table3") -> dict[str, Path]:
    """Table 3 in the paper's layout from an ablation sweep's per-variant result files of each dataset
    (``dataset_files[dataset][variant]``): a row per variant, per dataset a PSNR / SSIM / LPIPS column group, each
    cell the variant's mean over the view counts evaluated (paper: 3, 6 and 9). Markdown and CSV; with each
    variant's ``per_scene.json`` beside its results, also ``<stem>_intervals.md`` (a section per dataset) and
    ``<stem>_<dataset>_per_scene.csv``."""
    loaded = {dataset: {variant: load_results(path) for variant, path in files.items()}
              for dataset, files in dataset_files.items()}
    rows = {dataset: ablation_rows(results) for dataset, results in loaded.items()}
    variants = list(dict.fromkeys(variant for files in dataset_files.values() for variant in files))
    lpips_notes = {r.get(META_KEY, {}).get("lpips", "not recorded") for d in loaded.values() for r in d.values()}
    out_dir = Path(out_dir)
    label = {dataset: DATASET_LABELS.get(dataset, dataset) for dataset in dataset_files}
    md = ["| Variant | " + " | ".join(f"{label[d]} {METRIC_LABELS[m]}" for d in rows for m in HEADLINE_METRICS) + " |",
          "|---|" + "---|" * (len(rows) * len(HEADLINE_METRICS))]
    for variant in variants:
        cells = [_fmt(rows[d][variant][m], m) if variant in rows[d] else "–" for d in rows for m in HEADLINE_METRICS]
        md.append(f"| {variant} | " + " | ".join(cells) + " |")
    md += ["", "Each cell: the variant's mean over the view counts evaluated ("
           + "; ".join(f"{label[d]}: {_views_note(rows[d])}" for d in rows) + ").",
           _labelled("LPIPS", "; ".join(sorted(lpips_notes))) + "."]
    paths = {"md": out_dir / f"{stem}.md", "csv": out_dir / f"{stem}.csv"}
    with atomic_write(paths["md"]) as tmp:
        tmp.write_text("\n".join(md) + "\n")
    with atomic_write(paths["csv"]) as tmp, tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["variant", "dataset", "views_averaged", *HEADLINE_METRICS])
        for variant in variants:
            for dataset in (d for d in rows if variant in rows[d]):
                row = rows[dataset][variant]
                writer.writerow([variant, dataset, row["views"], *[_csv_value(row[m]) for m in HEADLINE_METRICS]])
    sections = []
    for dataset, files in dataset_files.items():
        scene_files = {variant: Path(path).parent / "per_scene.json" for variant, path in files.items()}
        if not all(f.is_file() for f in scene_files.values()):
            continue
        per_scene = {variant: load_results(f) for variant, f in scene_files.items()}
        chosen = {v: (per_scene[v], variant_method(v, loaded[dataset][v])) for v in files}
        sections.append(f"### {label[dataset]}\n\n" + ablation_intervals_markdown(chosen))
        paths[f"per_scene_{dataset}"] = write_per_scene_csv(
            {scene: {v: per_scene[v][scene][method] for v, (_, method) in chosen.items()}
             for scene in sorted(set.intersection(*(set(p) for p in per_scene.values())))},
            out_dir / f"{stem}_{dataset}_per_scene.csv", column="variant")
    if sections:
        paths["intervals"] = out_dir / f"{stem}_intervals.md"
        with atomic_write(paths["intervals"]) as tmp:
            tmp.write_text("\n".join(sections))
    return paths


def write_ablation_report(inputs: Mapping[str, Sequence[str | Path]], out_dir: str | Path) -> Path:
    """Table 3 from the evaluation folders (or ``results.json`` files) of an ablation sweep: ``inputs[dataset]``
    holds one per variant. A variant is named by the ``meta.variant`` its evaluation recorded, else by its folder
    name. Returns the markdown table's path."""
    dataset_files: dict[str, dict[str, Path]] = {}
    for dataset, folders in inputs.items():
        files = dataset_files.setdefault(dataset, {})
        for item in folders:
            path = Path(item)
            path = path / "results.json" if path.is_dir() or not path.suffix else path
            variant = load_results(path).get(META_KEY, {}).get("variant") or path.parent.name
            if variant in files:
                raise ValueError(f"variant {variant!r} appears twice for {dataset}: {files[variant]} and {path}")
            files[str(variant)] = path
    return write_ablation_table(dataset_files, out_dir)["md"]


def held_out_table_markdown(quality: Mapping) -> str:
    """The held-out clip table (``tracegs.eval.clips``): PSNR of the input R_s and of each restorer's output
    per student condition (K views, 3DGS snapshot), then the mean over conditions."""
    labels = list(quality["mean"])
    header = ["R_s condition"] + [
        "input R_s" if label == "input" else METHOD_LABELS.get(label, label) for label in labels
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    rows = [*quality["conditions"].items(), ("mean", quality["mean"])]
    for condition, row in rows:
        lines.append("| " + " | ".join([condition] + [_fmt(row[label], "psnr") for label in labels]) + " |")
    table = (
        "\n".join(lines)
        + f"\n\nPSNR (dB) against ground truth on {quality['clips']} held-out clips of "
        f"{', '.join(quality['scenes'])}; reference frames excluded; scene means, then the mean over scenes.\n"
    )
    return table + ("\n" + held_out_intervals_markdown(quality) if "per_scene" in quality else "")


def write_held_out_report(quality: Mapping, out_dir: str | Path) -> Path:
    """``held_out_clips.json`` and ``held_out_clips.md`` in ``out_dir``; returns the markdown path."""
    out_dir = Path(out_dir)
    write_json_atomic(dict(quality), out_dir / "held_out_clips.json")
    table = out_dir / "held_out_clips.md"
    with atomic_write(table) as tmp:
        tmp.write_text(held_out_table_markdown(quality))
    return table


# ---------------------------------------------------------------- images and video


def image_array(image: Tensor) -> np.ndarray:
    """[3,H,W] float in [0,1] -> the HxWx3 uint8 array an image file holds (:func:`to_uint8`)."""
    if image.dim() != 3 or image.shape[0] != 3:
        raise ValueError(f"expected an image of shape [3,H,W], got {tuple(image.shape)}")
    return to_uint8(image.detach().float()).permute(1, 2, 0).cpu().numpy()


def _upscale(image: np.ndarray, factor: int) -> np.ndarray:
    return image.repeat(factor, axis=0).repeat(factor, axis=1) if factor > 1 else image


def _label_strip(labels: Sequence[str], cell_width: int, height: int = 28) -> np.ndarray:
    """A white strip with one centred caption per column, drawn with matplotlib's Agg canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    dpi = 100
    fig = Figure(figsize=(cell_width * len(labels) / dpi, height / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    for i, label in enumerate(labels):
        fig.text((i + 0.5) / len(labels), 0.5, label, ha="center", va="center", fontsize=10)
    canvas.draw()
    strip = np.asarray(canvas.buffer_rgba())[..., :3]
    return np.ascontiguousarray(strip[:height, : cell_width * len(labels)])


def _row(images: Sequence[Tensor], factor: int, cell_width: int | None = None) -> np.ndarray:
    """The images side by side, upscaled by ``factor``; each centred on white in a cell ``cell_width`` wide where
    given (a grid whose rows differ in width: portrait and landscape views)."""
    cells = [_upscale(image_array(img), factor) for img in images]
    if cell_width is not None:
        cells = [np.pad(cell, ((0, 0), ((cell_width - cell.shape[1]) // 2, (cell_width - cell.shape[1] + 1) // 2),
                               (0, 0)), constant_values=255) for cell in cells]
    return np.concatenate(cells, axis=1)


def _upscale_factor(height: int, min_height: int) -> int:
    return max(1, math.ceil(min_height / height))


def save_qualitative_grid(columns: Mapping[str, Sequence[Tensor]], path: str | Path,
                          min_cell_height: int = 144) -> Path:
    """PNG grid: one column per entry of ``columns`` (e.g. 3DGS / baseline / TRACE-GS / GT), one row per
    test view, captions on top (:func:`qualitative_grid`)."""
    grid = qualitative_grid(columns, min_cell_height)
    path = Path(path)
    with atomic_write(path) as tmp:
        iio.imwrite(tmp, grid, extension=".png")
    return path


def qualitative_grid(columns: Mapping[str, Sequence[Tensor]], min_cell_height: int = 144) -> np.ndarray:
    """The grid of :func:`save_qualitative_grid` as an H x W x 3 uint8 array (tracegs-view shows one row of it).
    Small renders are upscaled (nearest) so the grid stays readable."""
    labels = list(columns)
    counts = {len(v) for v in columns.values()}
    if len(counts) != 1 or 0 in counts:
        raise ValueError(f"every grid column needs the same non-zero number of views, got {sorted(counts)}")
    images = [image for column in columns.values() for image in column]
    factor = _upscale_factor(min(image.shape[-2] for image in images), min_cell_height)
    cell_width = max(image.shape[-1] for image in images) * factor
    rows = [_row([columns[label][i] for label in labels], factor, cell_width) for i in range(counts.pop())]
    return np.concatenate([_label_strip(labels, cell_width), *rows], axis=0)


def save_frames(frames: Tensor, directory: str | Path) -> Path:
    """``frames`` [F,3,H,W] as ``frame_0000.png``, ... in ``directory`` (replaced whole, never half-written)."""
    directory = Path(directory)
    with atomic_directory(directory) as staging:
        for index, frame in enumerate(frames):
            iio.imwrite(staging / f"frame_{index:04d}.png", image_array(frame), extension=".png")
    return directory


def save_view_images(images: Mapping[int, Tensor], directory: str | Path) -> dict[int, Path]:
    """Each ``images[view]`` [3,H,W] as ``view_<view>.png`` in ``directory`` (replaced whole, never half-written);
    returns the path of each view's file."""
    directory = Path(directory)
    with atomic_directory(directory) as staging:
        for view, image in images.items():
            iio.imwrite(staging / f"view_{view:04d}.png", image_array(image), extension=".png")
    return {view: directory / f"view_{view:04d}.png" for view in images}


def video_extension() -> str:
    """``.mp4`` when imageio's ffmpeg plugin (``imageio-ffmpeg``) is installed, else ``.gif``."""
    return ".mp4" if importlib.util.find_spec("imageio_ffmpeg") is not None else ".gif"


def save_comparison_video(frames: Mapping[str, Tensor], path_stem: str | Path, fps: int = 8,
                          min_cell_height: int = 144) -> Path:
    """Side-by-side video of each method along a test trajectory; ``frames[label]`` is ``[F,3,H,W]``.

    Writes ``<path_stem>.mp4`` (ffmpeg) or ``<path_stem>.gif`` and returns the path written.
    """
    labels = list(frames)
    lengths = {int(v.shape[0]) for v in frames.values()}
    if len(lengths) != 1 or 0 in lengths:
        raise ValueError(f"every method needs the same non-zero number of frames, got {sorted(lengths)}")
    first = next(iter(frames.values()))
    factor = _upscale_factor(first.shape[-2], min_cell_height)
    strip = _label_strip(labels, first.shape[-1] * factor)
    stack = np.stack([
        np.concatenate([strip, _row([frames[label][i] for label in labels], factor)], axis=0)
        for i in range(lengths.pop())
    ])
    # H.264 (yuv420p) needs even frame sizes.
    stack = stack[:, : stack.shape[1] // 2 * 2, : stack.shape[2] // 2 * 2]
    ext = video_extension()
    path = Path(path_stem).with_suffix(ext)
    with atomic_write(path) as tmp:
        if ext == ".mp4":
            # The temporary name ends in .tmp, so name the container for ffmpeg explicitly.
            iio.imwrite(tmp, stack, extension=ext, plugin="FFMPEG", fps=fps, codec="libx264",
                        macro_block_size=1, output_params=["-f", "mp4"])
        else:
            iio.imwrite(tmp, stack, extension=ext, duration=1000.0 / fps, loop=0)
    return path


# ---------------------------------------------------------------- Fig. 6


def plot_per_step_quality(curves: Mapping[str, Sequence[float]], path: str | Path,
                          ylabel: str = "PSNR (dB) of predicted clean frames",
                          title: str = "Per-step restoration quality along the reverse trajectory",
                          bands: Mapping[str, tuple[Sequence[float], Sequence[float]]] | None = None,
                          steps: Sequence[int] | None = None,
                          xlabel: str = "denoising step (reverse trajectory)") -> Path:
    """Fig. 6: one line per variant (e.g. on-policy F vs off-policy E), x = denoising step 1..M (or ``steps``, e.g.
    optimiser steps of a learning curve); ``bands[label]`` = (low, high) per step shades that curve's 95%
    interval over scenes."""
    # A bare Figure renders through Agg without touching pyplot's global backend state.
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    if not curves:
        raise ValueError("no curves to plot")
    fig = Figure(figsize=(5.5, 3.5), dpi=120)
    ax = fig.add_subplot()
    for label, values in curves.items():
        x = list(steps) if steps is not None else range(1, len(values) + 1)
        (line,) = ax.plot(x, list(values), marker="o", markersize=3, label=label)
        if bands and label in bands:
            ax.fill_between(x, *bands[label], color=line.get_color(), alpha=0.2, linewidth=0)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(title="shaded: 95% interval over scenes" if bands else None, title_fontsize=7)
    fig.tight_layout()
    path = Path(path)
    with atomic_write(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
