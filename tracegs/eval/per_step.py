"""Per-step restoration quality along the reverse trajectory (main paper Fig. 6).

At every state z_{t_i} the restorer visits during its own M-step rollout, the clean clip it predicts,
x0_hat = predict_clean(z_{t_i}, v(z_{t_i}), t_i), is decoded and compared with per-frame ground truth.
On-policy (F) and off-policy (E) students should stay close early and separate late (Sec. 4.3).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from tracegs.eval.trajectory import ClipEncodings, Role, trajectory_diagnostics
from tracegs.restorer.sampler import RestorationPipeline


@torch.no_grad()
def per_step_psnr(pipeline: RestorationPipeline, frames: Tensor, ref_images: Tensor, captions: list[str],
                  ground_truth: Tensor, seed: int, steps: int | None = None,
                  frame_weights: Tensor | None = None) -> list[float]:
    """PSNR (dB, mean over target frames) of the decoded x0 prediction at each of the M reverse steps.

    ``frames``/``ground_truth`` are (B, F, 3, H, W) in [0, 1]; frames 0 and -1 are the reference views and
    are excluded, as everywhere in the evaluation. Element i is the prediction made at state z_{t_{M-i}}: the
    visited-state curve of ``tracegs.eval.trajectory``, from the deployment sampler's states and noise.
    ``frame_weights`` (F - 2, summing to 1) weigh the frames' mean; None, the plain mean.
    """
    if frames.shape != ground_truth.shape:
        raise ValueError(f"frames {tuple(frames.shape)} and ground truth {tuple(ground_truth.shape)} differ")
    bb = pipeline.backbone
    device = pipeline.device
    ref_2d, ref_3d = bb.reference_encoder(ref_images.to(device))
    shared = ClipEncodings(ref_2d, ref_3d, bb.text_encoder.encode(captions), ground_truth[:, 1:-1], frame_weights)
    student = Role(pipeline.adapter, bb.codec.encode(frames.to(device)))
    return trajectory_diagnostics(bb, student, shared, seed, steps).visited


def mean_curves(curves: Sequence[Mapping[str, Sequence[float]]]) -> dict[str, list[float]]:
    """Average per-step curves of several clip sets (scenes x view settings) label by label."""
    if not curves:
        raise ValueError("no per-step curves to average")
    labels = list(curves[0])
    out = {}
    for label in labels:
        stacked = torch.tensor([list(c[label]) for c in curves], dtype=torch.float64)
        out[label] = stacked.mean(0).tolist()
    return out
