"""Two diagnostics of the states Stage 2 trains on, measured along a restorer's own reverse trajectory.

Stage 2 supervises the student at the states it visits itself (main paper Eq. 4); variant E supervises it at
independently forward-noised states of the same grid instead. Whether that can matter at a given scale is a
measurable question, asked here of each step i of the M-step deployment trajectory, on clips with per-frame
ground truth (the clean prediction x0_hat = predict_clean(z, v(z, t), t) decoded and scored by PSNR):

- **exposure gap**: PSNR of x0_hat at the student's visited state z_{t_i} minus PSNR of x0_hat at the
  forward-noised state of the same clip at the same t_i, built from the same initial noise draw
  (z_fwd = add_noise(x0, eps, t_i), eps = z_{t_M}). It is zero at the first step, where both states are the
  pure noise eps, and stays near zero when the visited states are no different from forward-noised ones:
  then on- and off-policy supervision (F and E) see the same states.
- **teacher advantage**: PSNR of the teacher's x0_hat (conditioned on R_d, Eq. 5) minus the student's (on
  R_s) at the student's own states: what on-policy distillation (Eq. 6) can transfer at each step.

The visited-state curve itself is Fig. 6 (``tracegs.eval.per_step``); the trajectory is scored in
``tracegs.eval.trajectory``.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from rich.progress import track
from torch import Tensor

from tracegs.data import cache_keys
from tracegs.data.cache_keys import condition_key
from tracegs.data.datamodule import ClipRecord
from tracegs.eval.clips import held_out_clips, load_clip, mean_psnr, trajectory_frames
from tracegs.eval.trajectory import ClipEncodings, Role, trajectory_diagnostics
from tracegs.processes import WorkerPool, run_units
from tracegs.restorer.build import Backbone


@dataclass
class VariantRoles:
    """How one variant is diagnosed: its student's adapter, and its teacher's adapter and view count (the
    teacher condition R_d it was distilled from); ``distilled=False`` (variant A) has no teacher."""

    student: str | None
    teacher: str | None = None
    teacher_views: int | None = None
    distilled: bool = False


def _clip_batch(tensors: Mapping[str, Tensor], keys: Sequence[str]) -> Tensor:
    return torch.stack([tensors[cache_keys.latent(key)].float() for key in keys])


@dataclass
class _ClipJob:
    """Every variant diagnosed on one held-out clip; handed to forked workers by inheritance, never pickled."""

    backbone: Backbone
    variants: Mapping[str, VariantRoles]
    seed: int
    steps: int | None

    @torch.no_grad()
    def __call__(self, index: int, clip: ClipRecord) -> dict[str, dict]:
        tensors = load_clip(clip)
        conditions = clip.conditions()
        batch = len(conditions)
        truth = trajectory_frames(tensors, cache_keys.GROUND_TRUTH)
        shared = ClipEncodings(
            *(tensors[key].float().expand(batch, -1, -1) for key in (cache_keys.REF_2D, cache_keys.REF_3D,
                                                                      cache_keys.TEXT)),
            truth=truth.unsqueeze(0).expand(batch, -1, -1, -1, -1))
        clean = tensors[cache_keys.latent(cache_keys.TARGET)].float().unsqueeze(0)
        student_cond = _clip_batch(tensors, conditions)
        input_psnr = sum(mean_psnr(trajectory_frames(tensors, c), truth) for c in conditions) / batch
        records = {}
        for name, roles in self.variants.items():
            teacher = None
            if roles.distilled:
                key = condition_key(roles.teacher_views)
                if cache_keys.latent(key) not in tensors:
                    raise KeyError(f"{clip.path}: no teacher condition {key} for variant {name} (prepare the held-out "
                                   "cache with data.prepare.dense_views and student_final_fits covering it)")
                teacher = Role(roles.teacher, _clip_batch(tensors, [key] * batch))
            result = trajectory_diagnostics(self.backbone, Role(roles.student, student_cond), shared,
                                            self.seed + index, self.steps, clean=clean, teacher=teacher)
            records[name] = {"visited": result.visited, "noised": result.noised, "teacher": result.teacher,
                             "final": result.final, "input": input_psnr}
        return records


_FORKED_JOB: _ClipJob | None = None  # set in the parent just before forking the workers


def _forked_clip(index: int, clip: ClipRecord) -> dict[str, dict]:
    return _FORKED_JOB(index, clip)


def held_out_diagnostics(backbone: Backbone, variants: Mapping[str, VariantRoles], cache_dir: str | Path,
                         student_views: Sequence[int], seed: int = 0, steps: int | None = None,
                         progress: bool = True, workers: int = 1) -> dict:
    """Both diagnostics, the per-step curve, the final sample and the input R_s for every variant on every
    held-out clip of a prepared cache (``tracegs-prepare data.prepare.split=test``), at the student conditions
    of ``student_views`` (batched per clip, one noise seed per clip shared by every variant). With ``workers``
    > 1 (CPU only) the clips are spread over that many forked processes; the result is the same.

    Returns ``{"per_scene": {scene: {variant: {"visited": [..], "noised": [..], "teacher": [..] | None,
    "final": psnr, "input": psnr}}}, "conditions": [...], "clips": n, "steps": M}``: each scene's mean over its
    clips (and conditions), the unit of the report's intervals over scenes.
    """
    global _FORKED_JOB
    shards = [clip for clip in held_out_clips(cache_dir) if clip.views in student_views]
    if not shards:
        raise ValueError(f"{cache_dir}: no held-out clip at {list(student_views)} views")
    conditions = sorted({condition for clip in shards for condition in clip.conditions()})
    job = _ClipJob(backbone, variants, seed, steps)
    # Forked workers must not inherit a CUDA context; GPU runs go one clip at a time.
    workers = 1 if next(backbone.transformer.parameters()).is_cuda else min(workers, len(shards))
    pool = None
    if workers > 1:
        _FORKED_JOB = job
        pool = WorkerPool(workers, "fork")
    sums: dict = defaultdict(lambda: defaultdict(list))  # scene -> variant -> one record per clip
    try:
        results = run_units(pool, job if pool is None else _forked_clip,
                            list(enumerate(shards)))
        for clip, records in zip(shards, track(results, total=len(shards), description="trajectory "
                                                     "diagnostics", disable=not progress)):
            for name, record in records.items():
                sums[clip.scene][name].append(record)
    finally:
        if pool is not None:
            pool.shutdown()
        _FORKED_JOB = None
    return {
        "per_scene": {scene: {name: _mean_records(records) for name, records in by_variant.items()}
                      for scene, by_variant in sorted(sums.items())},
        "conditions": conditions,
        "clips": len(shards),
        "steps": len(next(iter(next(iter(sums.values())).values()))[0]["visited"]),
    }


def _mean_records(records: Sequence[Mapping]) -> dict:
    """The clip records of one scene and variant averaged field by field (curves step by step)."""
    out = {}
    for field in records[0]:
        values = [r[field] for r in records]
        if values[0] is None:
            out[field] = None
        elif isinstance(values[0], list):
            out[field] = [sum(step) / len(step) for step in zip(*values)]
        else:
            out[field] = sum(values) / len(values)
    return out
