"""Held-out clips of a captured scene, with per-frame ground truth (main paper Fig. 6 on Mip-NeRF 360).

A real capture has no ground-truth renderer, so a clip with per-frame ground truth must run through captured
cameras. The paper does not say how its held-out clips are built; the construction chosen here keeps
deployment's shape of a clip (TRACE-GS restores clips between two reference views, supplement A.5) and only
replaces the synthesised trajectory by the capture itself:

- capture order (``capture_order``) is the images' EXIF DateTimeOriginal when every image carries a valid
  one (ties broken by name), else the order of their names (a camera's counter, as Mip-NeRF 360's DSC names);
- for each student view count K, the K sparse views V_s of the scene's split (``data.splits``), in capture
  order, are paired as deployment chains them (``reference_pairs``: a closed loop);
- a clip runs from one reference view to the next through the captured images between them in capture order
  (around the loop for the closing pair), subsampled evenly (``splits.spread_evenly``) to
  ``frames_per_clip - 2`` interior frames, none of them in V_s;
- its cameras are those captured cameras, its ground truth their captured images (resized as the dataset's
  images are), its conditions the K-view fits rendered at those cameras, its references the two captured
  reference images.

Why: the interior frames are real photographs at real poses the K-view fit never saw, so the per-step curve
measures restoration of unseen views against their true pixels, the quantity Fig. 6 plots.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

import torch
from PIL import Image, UnidentifiedImageError

from tracegs.data.colmap import Scene
from tracegs.data.splits import SceneSplit, spread_evenly
from tracegs.splat.trajectory import reference_pairs


class CaptureTooShortError(ValueError):
    """A captured scene has too few images between two reference views for a held-out clip."""


EXIF_ORDER = "EXIF DateTimeOriginal"
NAME_ORDER = "image names"
_EXIF_IFD, _DATE_TIME_ORIGINAL = 0x8769, 0x9003


def exif_capture_time(path: Path) -> datetime | None:
    """The EXIF DateTimeOriginal of an image, None when it has none or an invalid one (an unset clock's zeros)."""
    try:
        with Image.open(path) as image:
            stamp = image.getexif().get_ifd(_EXIF_IFD).get(_DATE_TIME_ORIGINAL)
        return datetime.strptime(str(stamp).strip(), "%Y:%m:%d %H:%M:%S")
    except (OSError, UnidentifiedImageError, ValueError):
        return None


def capture_order(image_paths: Sequence[Path], image_names: Sequence[str]) -> tuple[list[int], str]:
    """Image indices in capture order, and the rule that gave it: EXIF DateTimeOriginal when every image has a
    valid one (one-second resolution, so ties go by name), else the name order (the scene's images are sorted by
    name), which a camera's file counter follows until it wraps."""
    stamps = [exif_capture_time(path) for path in image_paths]
    if all(stamps):
        return sorted(range(len(stamps)), key=lambda i: (stamps[i], image_names[i])), EXIF_ORDER
    return sorted(range(len(image_names)), key=lambda i: image_names[i]), NAME_ORDER


def between_in_capture_order(first: int, last: int, count: int, excluded: set[int]) -> list[int]:
    """Capture positions (``capture_order``) strictly after ``first`` and before ``last``, going forward around
    the loop of ``count`` images (the closing pair wraps past the last image), skipping ``excluded``."""
    steps = (last - first) % count or count
    return [index for index in ((first + k) % count for k in range(1, steps)) if index not in excluded]


def captured_clips(scene: Scene, split: SceneSplit, student_views: list[int], frames_per_clip: int,
                   repeat_frames: bool = False) -> list[dict]:
    """Every held-out clip of ``scene`` (construction: module docstring), K by K in ``student_views`` order:
    ``{"views": K, "refs": [a, b], "images": [a, ..., b], "cameras": [...], "capture_order": rule}``.

    Raises :class:`CaptureTooShortError` naming ``data.prepare.frames_per_clip`` when two consecutive reference
    views have fewer than ``frames_per_clip - 2`` captured images between them, unless ``repeat_frames``, which
    fills such a clip by repeating its captured images evenly (at least one is needed)."""
    interior = frames_per_clip - 2
    order, rule = capture_order(scene.image_paths, scene.image_names)
    position = {image: p for p, image in enumerate(order)}
    clips = []
    for views in student_views:
        references = sorted(split.views(views), key=position.__getitem__)
        sparse = {position[i] for i in references}
        for a, b in reference_pairs(len(references), None, torch.Generator()):
            first, last = references[a], references[b]
            candidates = [order[p] for p in between_in_capture_order(position[first], position[last], len(scene),
                                                                     sparse)]
            if len(candidates) < (1 if repeat_frames else interior):
                raise CaptureTooShortError(
                    f"data.prepare.frames_per_clip={frames_per_clip} needs {interior} captured images between "
                    f"reference views {scene.image_names[first]} and {scene.image_names[last]} of the {views}-view "
                    f"set, the capture has {len(candidates)} (data.prepare.held_out_repeat_frames=true repeats them)")
            images = [first, *spread_evenly(candidates, interior), last]
            clips.append({"views": views, "refs": [first, last], "images": images,
                          "cameras": [scene.cameras[i] for i in images], "capture_order": rule})
    return clips
