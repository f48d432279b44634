"""Restoring clips larger than the restorer's frames: a capture fitted at a size a person can look at (360 px on the
longer side by default) under a restorer that works at its own frame size (the embedded one at 48x72).

The paper restores at its backbone's frames (720x480), the size it fits and scores at, so it never needs this;
neither does GSFixer's release, which resizes every clip to the restorer's frames (``clip_size``). Two ways, by
``deploy.upscale`` (docs/your_capture.md measures both on a capture whose cameras are known):

- ``tiles``: overlapping tiles of the restorer's frame size, each restored as a clip of its own (the same frames
  of the same poses, cut at one place, with the reference images cut there too), blended with linear feathering
  that sums to one at every pixel, so a restorer that returns its input returns the clip unchanged;
- ``residual``: the clip resized to the restorer's frame and restored, and the correction it made (restored minus
  its input) upsampled and added to the full-size rendering, which keeps the rendering's finer detail.

A clip smaller than the restorer's frame in either direction is restored by ``residual`` whatever the setting: no
tile fits in it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import torch
import torch.nn.functional as F
from torch import Tensor

from tracegs.deploy.config import Upscale
from tracegs.deploy.restorers import Clip, ClipRestorer


def tile_starts(length: int, tile: int, overlap: float) -> list[int]:
    """Starts of the fewest tiles of ``tile`` pixels that cover [0, length) with neighbours sharing at least
    ``overlap`` of a tile, spread evenly: the first at 0, the last at ``length - tile``."""
    if length <= tile:
        return [0]
    count = math.ceil((length - tile) / (tile * (1.0 - overlap))) + 1
    return [round(i * (length - tile) / (count - 1)) for i in range(count)]


def feather(tile: int) -> Tensor:
    """Linear feathering over one tile's side: a tent, highest in the middle, positive up to its edges (so a pixel
    that only one tile covers, at the clip's border, keeps that tile's value once the weights are normalised)."""
    position = torch.arange(tile, dtype=torch.float32) + 0.5
    return torch.minimum(position, tile - position) / (tile / 2.0)


def tile_boxes(size: Sequence[int], tile: Sequence[int], overlap: float) -> list[tuple[int, int]]:
    """(top, left) of each tile of ``tile`` [height, width] over an image of ``size`` [height, width]."""
    return [(top, left) for top in tile_starts(size[0], tile[0], overlap)
            for left in tile_starts(size[1], tile[1], overlap)]


def cut_tiles(images: Tensor, boxes: Sequence[tuple[int, int]], tile: Sequence[int]) -> list[Tensor]:
    """``images`` [..., H, W] cut at each box into [..., tile height, tile width]."""
    return [images[..., top:top + tile[0], left:left + tile[1]] for top, left in boxes]


def blend_tiles(tiles: Sequence[Tensor], boxes: Sequence[tuple[int, int]], size: Sequence[int]) -> Tensor:
    """The tiles [..., h, w] put back at their boxes in an image of ``size`` [height, width], each pixel the
    feathered (``feather``) mean of the tiles that cover it."""
    height, width = tiles[0].shape[-2:]
    weight = feather(height)[:, None] * feather(width)[None, :]
    total = tiles[0].new_zeros((*tiles[0].shape[:-2], *size))
    weights = tiles[0].new_zeros(tuple(size))
    for piece, (top, left) in zip(tiles, boxes):
        total[..., top:top + height, left:left + width] += piece * weight
        weights[top:top + height, left:left + width] += weight
    return total / weights


def resized(images: Tensor, size: Sequence[int]) -> Tensor:
    """``images`` [N,3,H,W] at ``size`` [height, width], bilinear with antialiasing when downsizing."""
    if tuple(images.shape[-2:]) == tuple(size):
        return images
    return F.interpolate(images, size=tuple(size), mode="bilinear", align_corners=False, antialias=True)


def restore_at_frame(restorer: ClipRestorer, clips: Sequence[Clip], seed: int, frame: Sequence[int] | None,
                     upscale: Upscale, overlap: float) -> list[Tensor]:
    """Each clip's restored frames at the clip's own size, the restorer seeing frames of ``frame`` [height, width]
    only (module docstring); ``frame=None`` or clips already at it: restored as they are, in one call."""
    if frame is None or all(tuple(clip.frames.shape[-2:]) == tuple(frame) for clip in clips):
        return restorer.restore(clips, seed=seed)
    pieces: list[Clip] = []
    layouts: list[list[tuple[int, int]] | None] = []
    for clip in clips:
        size = clip.frames.shape[-2:]
        if upscale == Upscale.tiles and size[0] >= frame[0] and size[1] >= frame[1]:
            boxes = tile_boxes(size, frame, overlap)
            pieces += [replace(clip, frames=frames, references=references) for frames, references in
                       zip(cut_tiles(clip.frames, boxes, frame), cut_tiles(clip.references, boxes, frame))]
            layouts.append(boxes)
        else:
            pieces.append(replace(clip, frames=resized(clip.frames, frame), references=resized(clip.references, frame)))
            layouts.append(None)
    restored = restorer.restore(pieces, seed=seed)  # every tile of every clip in one call: the restorer batches
    out, index = [], 0
    for clip, boxes in zip(clips, layouts):
        size = clip.frames.shape[-2:]
        if boxes is None:
            correction = restored[index] - pieces[index].frames
            out.append((clip.frames + resized(correction, size)).clamp(0, 1))
            index += 1
        else:
            out.append(blend_tiles(restored[index:index + len(boxes)], boxes, size).clamp(0, 1))
            index += len(boxes)
    return out
