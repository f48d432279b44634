"""The clean prediction along a restorer's own reverse trajectory, scored against ground truth at every step:
at the states it visits (Fig. 6), at the forward-noised states of the same noise, and by a teacher at its
states. ``tracegs.eval.diagnostics`` turns these into the exposure gap and the teacher advantage on held-out
clips; ``tracegs.eval.per_step`` into the Fig. 6 curve.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio

from tracegs.restorer.build import Backbone
from tracegs.restorer.sampler import (
    first_state,
    guided_prediction,
    initial_noise,
    negative_text,
    solve,
    using_adapter,
)


@dataclass
class Role:
    """A restorer in one role: its adapter on the shared backbone (None = the bare base) and the condition
    latents it sees, (B, f, C, h, w) (R_s for the student, R_d for the teacher)."""

    adapter: str | None
    condition: Tensor


@dataclass
class ClipEncodings:
    """What every role shares for a batch of B conditions of one clip: reference and text encodings (B rows)
    and the ground truth of the trajectory frames, (B, F - 2, 3, H, W) in [0, 1]: the two reference frames at
    the clip's ends are excluded from every score, as everywhere in the evaluation."""

    ref_2d: Tensor
    ref_3d: Tensor
    text: Tensor
    truth: Tensor
    # Weights of the F - 2 frames in each clip's mean (``frame_mean``); None: the plain mean.
    frame_weights: Tensor | None = None


@dataclass
class TrajectoryDiagnostics:
    """Per reverse step (element i: the state z_{t_{M-i}}), each a mean over the batch's conditions."""

    visited: list[float]  # the student's x0_hat at its own states (Fig. 6)
    noised: list[float] | None  # its x0_hat at the forward-noised states (None: no clean latent given)
    teacher: list[float] | None  # the teacher's x0_hat at the student's states (None: no teacher given)
    final: float  # the decoded final sample (the restorer's output)

    @property
    def exposure_gap(self) -> list[float] | None:
        return None if self.noised is None else [a - b for a, b in zip(self.visited, self.noised)]

    @property
    def teacher_advantage(self) -> list[float] | None:
        return None if self.teacher is None else [a - b for a, b in zip(self.teacher, self.visited)]


def frame_mean(per_frame: Tensor, weights: Tensor | None) -> Tensor:
    """Mean over the last (frame) dimension: plain, or with ``weights`` (one per frame, summing to 1), which a
    padded held-out clip uses to count each distinct ground-truth frame once (``eval.clips.distinct_frame_weights``)."""
    if weights is None:
        return per_frame.mean(-1)
    return (per_frame.double() * weights.to(per_frame.device, torch.float64)).sum(-1)


def _psnr(backbone: Backbone, latents: Tensor, truth: Tensor, weights: Tensor | None = None) -> float:
    """PSNR of decoded latents' trajectory frames (the reference frames at the ends dropped) against ``truth``:
    per clip over its frames (``frame_mean``), then the mean over the batch."""
    frames = backbone.codec.decode(latents).clamp(0, 1)[:, 1:-1]
    per_frame = peak_signal_noise_ratio(frames.flatten(0, 1), truth.flatten(0, 1).to(frames),
                                        data_range=1.0, reduction="none", dim=(1, 2, 3))
    return float(frame_mean(per_frame.view(frames.shape[0], -1), weights).mean())


@torch.no_grad()
def trajectory_diagnostics(backbone: Backbone, student: Role, shared: ClipEncodings, seed: int,
                           steps: int | None = None, clean: Tensor | None = None,
                           teacher: Role | None = None) -> TrajectoryDiagnostics:
    """The student's M-step deployment trajectory from the noise of ``seed`` (the deployment sampler's states,
    ``sampler.sample``), with the clean prediction scored at every visited state; with ``clean`` (the clip's
    clean latents x0) also at the forward-noised states of the same noise, and with ``teacher`` the teacher's
    prediction at the visited states. Guidance is deployment's (``backbone.sampler.guidance_scale``)."""
    model, schedule = backbone.transformer, backbone.schedule
    device = next(model.parameters()).device
    guidance = backbone.cfg.sampler.guidance_scale
    grid = schedule.timesteps(steps or backbone.cfg.schedule.deploy_steps)
    ref_2d, ref_3d, text = (x.to(device) for x in (shared.ref_2d, shared.ref_3d, shared.text))
    uncond_text = negative_text(backbone, guidance)

    def predict(role: Role, z: Tensor, t: Tensor) -> Tensor:
        with using_adapter(model, role.adapter):
            return guided_prediction(model, z, role.condition.to(device), t, text, ref_2d, ref_3d, guidance,
                                     uncond_text=uncond_text).velocity

    def score(z: Tensor, v: Tensor, t: Tensor) -> float:
        return _psnr(backbone, schedule.predict_clean(z, v.float(), t), shared.truth, shared.frame_weights)

    noise = initial_noise(student.condition.shape, torch.Generator().manual_seed(seed), device)
    velocities: list[Tensor] = []

    def student_velocity(_: int, z: Tensor, t: Tensor) -> Tensor:
        velocities.append(predict(student, z, t).float())
        return velocities[-1]

    # The solver's own velocity at each visited state is the student's prediction there: no second forward.
    states = solve(schedule, grid, first_state(schedule, noise, backbone.cfg.sampler.temperature), student_velocity,
                   keep_states=True)
    visited, noised, taught = [], [], []
    for z, v, t in zip(states[:-1], velocities, grid[:-1]):
        t_batch = t.expand(z.shape[0]).to(device)
        visited.append(score(z, v, t_batch))
        if clean is not None:
            forward = schedule.add_noise(clean.to(device).expand_as(z), noise, t_batch)
            noised.append(score(forward, predict(student, forward, t_batch), t_batch))
        if teacher is not None:
            taught.append(score(z, predict(teacher, z, t_batch), t_batch))
    final = _psnr(backbone, states[-1], shared.truth, shared.frame_weights)
    return TrajectoryDiagnostics(visited, noised if clean is not None else None,
                                 taught if teacher is not None else None, final)
