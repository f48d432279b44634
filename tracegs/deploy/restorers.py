"""Clip restorers used by the restore-refine loop: the diffusion student/baseline, and a ground-truth oracle.

The loop only needs ``restore(clips) -> frames``; a clip carries its rendered frames, the poses they were
rendered at, its two reference images (observed views at the clip ends) and its caption (data/captions.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from tracegs.splat.cameras import Camera
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.render import render


@dataclass
class Clip:
    """One restoration unit: ``frames`` [F,3,H,W] in [0,1] rendered at ``cameras`` (frame 0 and -1 at the
    reference views), ``references`` [2,3,H,W] the captured images of those reference views, both at the
    restorer's size (``deploy.clip_size``), which may differ from the cameras'."""

    frames: Tensor
    cameras: list[Camera]
    references: Tensor
    caption: str


class ClipRestorer(Protocol):
    def restore(self, clips: Sequence[Clip], seed: int) -> list[Tensor]:
        """Restored frames [F,3,H,W] in [0,1] per clip, same order and shape as the inputs."""
        ...


class DiffusionRestorer:
    """The deployed restorer (student adapter, or the baseline restorer) over its full M-step schedule.

    ``pipeline`` is a ``tracegs.restorer.sampler.RestorationPipeline``; clips are batched ``batch`` at a
    time, with a distinct seed per batch so clips never share their initial noise.
    """

    def __init__(self, pipeline, batch: int = 4, identity: str = "", steps: int | None = None):
        self.pipeline = pipeline
        self.batch = batch
        self.steps = steps  # None = the full M-step deployment schedule of the backbone config
        # What distinguishes this restorer's weights (e.g. adapter file digests): evaluation reruns a
        # finished unit when it changes.
        self.identity = identity

    def restore(self, clips: Sequence[Clip], seed: int) -> list[Tensor]:
        restored: list[Tensor] = []
        for start in range(0, len(clips), self.batch):
            chunk = clips[start : start + self.batch]
            frames = torch.stack([c.frames for c in chunk])
            refs = torch.stack([c.references for c in chunk])
            out = self.pipeline.restore(frames, refs, [c.caption for c in chunk], seed=seed + start, steps=self.steps)
            restored.extend(out.clamp(0, 1).unbind(0))
        return restored


class GroundTruthRestorer:
    """Oracle restorer for scenes whose true Gaussians are known (the synthetic benchmark): it ignores
    the rendered frames and returns ground truth at the same poses. An upper bound for the loop, and the
    restorer the deployment tests use to check that repair rounds help when restoration is right."""

    def __init__(self, gt_model: GaussianModel, background: Sequence[float] = (0.0, 0.0, 0.0),
                 sh_degree: int | None = 0):
        self.gt_model = gt_model
        self.background = torch.tensor(list(background), dtype=torch.float32)
        self.sh_degree = sh_degree  # the synthetic benchmark's ground truth is view-independent (degree 0)
        self.identity = f"ground-truth oracle ({len(gt_model)} Gaussians)"

    @torch.no_grad()
    def restore(self, clips: Sequence[Clip], seed: int) -> list[Tensor]:
        return [
            torch.stack([render(self.gt_model, cam, background=self.background, sh_degree=self.sh_degree).image
                         for cam in clip.cameras]).clamp(0, 1)
            for clip in clips
        ]

