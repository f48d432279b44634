"""Deployment-time restore-refine loop (Algorithm 1 bottom; supplement A.5).

G <- 3DGS(V_s) (sparse-only cold start up to the first repair iteration); then at each repair iteration
the round's trajectory P^(r) is resampled (ellipse + bridges, round-dependent scale/height, random
phase), rendered, split into clips anchored by two observed reference views, restored by the deployed
restorer over its full schedule, and the restored frames *replace* the pseudo-observation set at the
poses they were rendered at (Eq. supp-round-pseudo-set). Optimisation continues with
L = L_sparse + w_reg(j) L_pseudo (Eq. supp-refinement-objective); captured views keep unit weight.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import torch

from tracegs.data.captions import clip_caption, release_captioner
from tracegs.deploy.config import KeptFrames, RefinementConfig
from tracegs.deploy.restorers import Clip, ClipRestorer
from tracegs.deploy.tiles import restore_at_frame
from tracegs.splat.cameras import Camera, reframe_image
from tracegs.splat.config import GaussianFitConfig
from tracegs.splat.fit import GaussianFitter, View, camera_extent
from tracegs.splat.gaussians import GaussianModel
from tracegs.splat.render import render_clip
from tracegs.splat.trajectory import round_clips, with_captured_ends


def pseudo_weight(j: int, first_repair: int, total: int, lambda_reg: float = 1.0) -> float:
    """w_reg(j) of Eq. supp-pseudo-weight: 0 before the first repair, then one global half-sine
    lambda_reg * sin(pi (j - first) / (J - first)) that peaks at the midpoint and is 0 again at J.
    It is defined once over the whole refinement interval and never restarted per repair round."""
    if not 0 < first_repair < total:
        raise ValueError(f"need 0 < first_repair ({first_repair}) < total ({total})")
    if j < first_repair:
        return 0.0
    phase = min(j - first_repair, total - first_repair) / (total - first_repair)
    # sin(pi) is 1.2e-16 in floating point; the schedule must vanish exactly at J.
    return 0.0 if phase >= 1.0 else lambda_reg * math.sin(math.pi * phase)


@dataclass
class RepairRound:
    """What one repair round produced: its pseudo-observation set (restored frames at their poses)."""

    index: int
    iteration: int
    clips: list[Clip]  # the rendered clips the restorer saw
    pseudo: list[View]  # replaces every earlier pseudo view


def to_clip_size(images: torch.Tensor, size: Sequence[int] | None) -> torch.Tensor:
    """Images [N,3,H,W] resized bilinearly to the restorer's ``size`` [height, width] where they differ, as GSFixer's
    release resizes its renders (gsfixer/extrapolation/outpaint/base.py l. 63) and captured ends (sparse.py
    l. 287-296); unchanged when ``size`` is None."""
    if size is None or tuple(images.shape[-2:]) == tuple(size):
        return images
    return torch.nn.functional.interpolate(images, size=tuple(size), mode="bilinear", align_corners=False)


def clip_frame(cameras: Sequence[Camera], restorer_frame: Sequence[int] | None) -> tuple[int, int]:
    """(width, height) every clip is rendered at: the restorer's frame's aspect ratio with the cameras' longest
    side, or the first camera's size without ``restorer_frame``. One size for every clip and frame, whatever the
    captured views' orientations: a portrait view is a clip's end as its ``Camera.reframed`` landscape frame."""
    if restorer_frame is None:
        return cameras[0].width, cameras[0].height
    height, width = restorer_frame
    scale = max(max(c.width, c.height) for c in cameras) / max(height, width)
    return round(width * scale), round(height * scale)


def render_round_clips(fitter: GaussianFitter, captured: Sequence[View], round_index: int, cfg: RefinementConfig,
                       fit_cfg: GaussianFitConfig, caption: str, generator: torch.Generator) -> list[Clip]:
    """Resample the round's trajectory P^(r) and render G^(r) along it (Eq. supp-round-rendering), as clips
    whose two ends are observed reference views (their captured images become the clip's references), both at
    ``clip_frame`` (the captured cameras and images reframed to it, unchanged where they have its size), then at
    the restorer's ``cfg.clip_size`` (``to_clip_size``).
    Frames come from ``render_clip`` and captions from ``clip_caption`` on each clip's first frame, as in
    prepare; ``caption`` is the scene's own caption (its caption.txt, "" when it has none)."""
    width, height = clip_frame([v.camera for v in captured], cfg.restorer_frame)
    clips = []
    for (a, b), cams in round_clips([v.camera.reframed(width, height) for v in captured], round_index,
                                    cfg.trajectory, cfg.max_clips_per_round, generator):
        frames = to_clip_size(render_clip(fitter.model, cams, fit_cfg, fitter.iteration), cfg.clip_size)
        references = to_clip_size(torch.stack([reframe_image(captured[i].image, width, height) for i in (a, b)]),
                                  cfg.clip_size)
        if cfg.trajectory.captured_ends:
            frames = with_captured_ends(frames, references)
        clips.append(Clip(frames=frames, cameras=list(cams), references=references,
                          caption=clip_caption(cfg.captions, frames[0], caption)))
    release_captioner()  # the round is captioned: BLIP-2 leaves the accelerator before the restorer denoises
    return clips


def repair_round(fitter: GaussianFitter, captured: Sequence[View], restorer: ClipRestorer, round_index: int,
                 cfg: RefinementConfig, fit_cfg: GaussianFitConfig, caption: str,
                 generator: torch.Generator) -> RepairRound:
    """One repair call: render the round's clips, restore every clip (at the restorer's frame size where
    ``cfg.restorer_frame`` sets one: ``restore_at_frame``), pool the restored target frames into
    the new pseudo-set (Eq. supp-round-pseudo-set): every frame (``kept_frames=every``, GSFixer's release), or
    only those between the two clip ends, which are the reference views themselves, already supervised by
    L_sparse (``between_ends``)."""
    clips = render_round_clips(fitter, captured, round_index, cfg, fit_cfg, caption, generator)
    seed = int(torch.randint(0, 2**31 - 1, (1,), generator=generator))
    with torch.no_grad():
        restored = restore_at_frame(restorer, clips, seed, cfg.restorer_frame, cfg.upscale, cfg.tile_overlap)
    if len(restored) != len(clips):
        raise RuntimeError(f"restorer returned {len(restored)} clips for {len(clips)}")
    kept = slice(None) if cfg.kept_frames == KeptFrames.every else slice(1, -1)
    pseudo = [
        View(image=frame, camera=cam)
        for clip, frames in zip(clips, restored)
        for frame, cam in zip(frames[kept], clip.cameras[kept])
    ]
    return RepairRound(index=round_index, iteration=fitter.iteration, clips=clips, pseudo=pseudo)


def cold_start(captured: Sequence[View], init: GaussianModel, cfg: RefinementConfig, fit_cfg: GaussianFitConfig,
               progress: bool = False) -> GaussianFitter:
    """The sparse-only cold start G <- 3DGS(V_s), trained up to the first repair iteration.

    Identical for every method, so evaluation fits it once per (scene, K) and branches it (``refine``
    deep-copies it) for 3DGS, the baseline restorer and TRACE-GS. ``cfg`` is validated once by the caller (an
    entry point: ``restore_refine``, evaluation, deployment, the training callback), not per unit."""
    fit_cfg = copy.deepcopy(fit_cfg)
    fit_cfg.iterations = cfg.total_iters  # schedules (lr decay, densification) span the whole J
    # Scene extent from V_s alone, as the sparse fits of the training data were made (``fit_gaussians``).
    fitter = GaussianFitter(init.clone(), fit_cfg, camera_extent([v.camera for v in captured]))
    with _seeded_global_rng(cfg.seed):
        fitter.train_until(cfg.repair_iters[0], list(captured), progress=progress)
    return fitter


@contextlib.contextmanager
def _seeded_global_rng(seed: int) -> Iterator[None]:
    """gsplat's densification samples split positions from torch's global RNG; seed it for this run only,
    so every method branched from one cold start sees the same randomness whatever ran before."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


def refine(cold: GaussianFitter, captured: Sequence[View], restorer: ClipRestorer | None, cfg: RefinementConfig,
           fit_cfg: GaussianFitConfig, caption: str = "", seed: int | None = None,
           on_round: Callable[[RepairRound], None] | None = None, progress: bool = False) -> GaussianModel:
    """Continue a cold start to J. ``restorer=None`` is plain 3DGS (L_sparse only, no repair rounds).

    ``cold`` is left untouched (deep-copied), so several methods can branch from one cold start. ``cfg`` is
    validated once by the caller, not per method.
    """
    if cold.iteration != cfg.repair_iters[0]:
        raise ValueError(f"cold start is at iteration {cold.iteration}, expected the first repair "
                         f"iteration {cfg.repair_iters[0]}")
    fitter = copy.deepcopy(cold)
    captured = list(captured)
    seed = cfg.seed if seed is None else seed
    with _seeded_global_rng(seed + 1):
        if restorer is None:
            fitter.train_until(cfg.total_iters, captured, progress=progress)
        else:
            _repair_and_train(fitter, captured, restorer, cfg, fit_cfg, caption, seed, on_round, progress)
    return fitter.model


def _repair_and_train(fitter: GaussianFitter, captured: list[View], restorer: ClipRestorer, cfg: RefinementConfig,
                      fit_cfg: GaussianFitConfig, caption: str, seed: int,
                      on_round: Callable[[RepairRound], None] | None, progress: bool) -> None:
    """The N_r repair rounds, each followed by optimisation with L_sparse + w_reg(j) L_pseudo up to the
    next repair iteration (or J)."""
    generator = torch.Generator().manual_seed(seed)
    weight = functools.partial(pseudo_weight, first_repair=cfg.repair_iters[0], total=cfg.total_iters,
                               lambda_reg=cfg.lambda_reg)
    ends = list(cfg.repair_iters[1:]) + [cfg.total_iters]
    for round_index, end in enumerate(ends):
        current = repair_round(fitter, captured, restorer, round_index, cfg, fit_cfg, caption, generator)
        if on_round is not None:
            on_round(current)
        # Replace, never accumulate: only this round's restorations are pseudo-observations.
        fitter.train_until(end, captured, pseudo=current.pseudo, pseudo_weight=weight, progress=progress)


def restore_refine(captured: Sequence[View], restorer: ClipRestorer | None, cfg: RefinementConfig,
                   fit_cfg: GaussianFitConfig, init: GaussianModel, caption: str = "",
                   seed: int | None = None, on_round: Callable[[RepairRound], None] | None = None,
                   progress: bool = False) -> GaussianModel:
    """Algorithm 1 (bottom) end to end: cold start from V_s, then N_r repair rounds up to J."""
    cfg.validate()
    cold = cold_start(captured, init, cfg, fit_cfg, progress=progress)
    return refine(cold, captured, restorer, cfg, fit_cfg, caption, seed, on_round, progress)
