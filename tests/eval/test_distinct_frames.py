"""Fig. 6 on held-out clips (tracegs/eval/clips.py): each distinct ground-truth frame counted once, padded clips
reported apart, K = 3 beside the mean over K, and the capture-order rule (tracegs/data/held_out.py)."""

from pathlib import Path

import pytest
import torch
from PIL import Image

from tracegs.data import cache_keys
from tracegs.data.datamodule import ClipRecord
from tracegs.data.held_out import EXIF_ORDER, NAME_ORDER, capture_order
from tracegs.eval.clips import (
    ClipCurves,
    distinct_frame_weights,
    mean_psnr,
    per_step_breakdown,
    per_step_breakdown_markdown,
)


def record(images: list[int] | None) -> ClipRecord:
    metadata = {} if images is None else {cache_keys.META_CAPTURED_IMAGES: str(images)}
    return ClipRecord("ring", 0, Path("clip.safetensors"), 3, (0, 9), "text.safetensors", frozenset(), metadata)


def test_a_repeated_captured_image_shares_one_frame_weight():
    assert distinct_frame_weights(record(None)) is None  # a rendered trajectory: every frame its own
    assert distinct_frame_weights(record([0, 4, 5, 6, 9])) is None  # unpadded: the plain mean
    padded = record([0, 5, 5, 5, 6, 9])
    assert padded.padded and not record([0, 4, 5, 6, 9]).padded
    assert distinct_frame_weights(padded).tolist() == pytest.approx([1 / 6, 1 / 6, 1 / 6, 1 / 2])


def test_clip_psnr_scores_each_distinct_ground_truth_frame_once():
    g = torch.Generator().manual_seed(0)
    image_5, image_6 = torch.rand(2, 3, 8, 8, generator=g)
    truth = torch.stack([image_5, image_5, image_5, image_6])  # image 5 repeated three times to fill the clip
    frames = truth.clone()
    frames[:3] = (frames[:3] + 0.05).clamp(0, 1)  # copies of image 5 restored worse than image 6
    frames[3] = (frames[3] + 0.2).clamp(0, 1)
    per_frame = [mean_psnr(f[None], t[None]) for f, t in zip(frames, truth)]
    weights = distinct_frame_weights(record([0, 5, 5, 5, 6, 9]))
    distinct = (sum(per_frame[:3]) / 3 + per_frame[3]) / 2
    assert mean_psnr(frames, truth, weights) == pytest.approx(distinct)
    assert mean_psnr(frames, truth) != pytest.approx(distinct)  # the plain mean counts image 5 three times


def test_breakdown_reports_padded_and_unpadded_clips_apart_and_k3_alone():
    clips = [ClipCurves("a", 3, False, NAME_ORDER, {"F": [10.0, 20.0]}),
             ClipCurves("a", 3, True, NAME_ORDER, {"F": [12.0, 22.0]}),
             ClipCurves("a", 6, True, NAME_ORDER, {"F": [14.0, 30.0]}),
             ClipCurves("b", 3, False, EXIF_ORDER, {"F": [16.0, 24.0]})]
    rows = {(r["clips"], r["views"]): r for r in per_step_breakdown(clips)["rows"]}
    assert {key: row["count"] for key, row in rows.items()} == {
        ("all", "mean over K"): 4, ("all", "K = 3"): 3, ("unpadded", "mean over K"): 2, ("unpadded", "K = 3"): 2,
        ("padded", "mean over K"): 2, ("padded", "K = 3"): 1}
    # K = 3: scene a's mean of its two clips (11, 21), then the mean over scenes with b (16, 24).
    assert rows[("all", "K = 3")]["curves"] == {"F": [13.5, 22.5]}
    assert rows[("all", "mean over K")]["curves"] == {"F": [13.75, 26.25]}  # K = 3 and K = 6 (14, 30) averaged
    assert rows[("unpadded", "mean over K")]["curves"] == {"F": [13.0, 22.0]}
    assert rows[("padded", "mean over K")]["curves"] == {"F": [13.0, 26.0]}
    markdown = per_step_breakdown_markdown(per_step_breakdown(clips))
    assert "| padded | K = 3 | 1 | F | 12.00 | 22.00 | 12.00 22.00 |" in markdown
    assert f"Capture order: {NAME_ORDER} (a); {EXIF_ORDER} (b)." in markdown
    empty = per_step_breakdown(clips[:1])["rows"]
    assert [(r["clips"], r["views"]) for r in empty if r["curves"] is None] == [("padded", "mean over K"),
                                                                                 ("padded", "K = 3")]


def write_image(path: Path, taken: str | None) -> Path:
    exif = Image.Exif()
    if taken is not None:
        exif.get_ifd(0x8769)[0x9003] = taken
    Image.new("RGB", (4, 4)).save(path, exif=exif)
    return path


def test_capture_order_follows_exif_timestamps_when_every_image_has_one(tmp_path):
    names = ["DSC09998.JPG", "DSC09999.JPG", "DSC00001.JPG", "DSC00002.JPG"]  # the camera's counter wrapped
    names_sorted = sorted(names)
    stamps = {"DSC09998.JPG": "2021:05:01 10:00:00", "DSC09999.JPG": "2021:05:01 10:00:01",
              "DSC00001.JPG": "2021:05:01 10:00:01", "DSC00002.JPG": "2021:05:01 10:00:03"}
    paths = [write_image(tmp_path / name, stamps[name]) for name in names_sorted]
    order, rule = capture_order(paths, names_sorted)
    # Timestamps first; DSC00001 and DSC09999 share a second, so the name breaks the tie.
    assert rule == EXIF_ORDER and [names_sorted[i] for i in order] == [
        "DSC09998.JPG", "DSC00001.JPG", "DSC09999.JPG", "DSC00002.JPG"]


@pytest.mark.parametrize("missing", [None, "0000:00:00 00:00:00"])
def test_capture_order_falls_back_to_names_unless_every_image_has_a_valid_timestamp(tmp_path, missing):
    names = ["a.jpg", "b.jpg", "c.jpg"]
    paths = [write_image(tmp_path / "a.jpg", "2021:05:01 10:00:09"), write_image(tmp_path / "b.jpg", missing),
             write_image(tmp_path / "c.jpg", "2021:05:01 10:00:01")]
    assert capture_order(paths, names) == ([0, 1, 2], NAME_ORDER)
