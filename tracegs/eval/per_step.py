"""Per-step restoration quality along the reverse trajectory (main paper Fig. 6).

At every state z_{t_i} the restorer visits during its own M-step rollout, the clean clip it predicts,
x0_hat = predict_clean(z_{t_i}, v(z_{t_i}), t_i), is decoded and compared with per-frame ground truth.
On-policy (F) and off-policy (E) students should stay close early and separate late (Sec. 4.3).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio

from tracegs.restorer.sampler import RestorationPipeline, guided_prediction, sample, using_adapter


@torch.no_grad()
def per_step_psnr(pipeline: RestorationPipeline, frames: Tensor, ref_images: Tensor, captions: list[str],
                  ground_truth: Tensor, seed: int, steps: int | None = None) -> list[float]:
    """PSNR (dB, mean over target frames) of the decoded x0 prediction at each of the M reverse steps.

    ``frames``/``ground_truth`` are (B, F, 3, H, W) in [0, 1]; frames 0 and -1 are the reference views and
    are excluded, as everywhere in the evaluation. Element i is the prediction made at state z_{t_{M-i}}.
    """
    if frames.shape != ground_truth.shape:
        raise ValueError(f"frames {tuple(frames.shape)} and ground truth {tuple(ground_truth.shape)} differ")
    bb, cfg = pipeline.backbone, pipeline.backbone.cfg
    device = pipeline.device
    steps = steps or cfg.schedule.deploy_steps
    guidance = cfg.sampler.guidance_scale
    cond = bb.codec.encode(frames.to(device))
    ref_2d, ref_3d = bb.reference_encoder(ref_images.to(device))
    ref_2d, ref_3d = ref_2d.to(device), ref_3d.to(device)
    text = bb.text_encoder.encode(captions).to(device)
    grid = bb.schedule.timesteps(steps)
    target = ground_truth[:, 1:-1].flatten(0, 1).to(device)
    curve = []
    with using_adapter(bb.transformer, pipeline.adapter):
        _, states = sample(bb.transformer, bb.schedule, cond, ref_2d, ref_3d, text, steps, guidance,
                           torch.Generator().manual_seed(seed), return_states=True)
        for z, t in zip(states[:-1], grid[:-1]):
            t_batch = t.expand(z.shape[0]).to(device)
            # Re-evaluating v at the visited state (one extra forward per step) gives the exact x0 the
            # solver is heading for; the sampler itself only keeps the states.
            v = guided_prediction(bb.transformer, z, cond, t_batch, text, ref_2d, ref_3d, guidance).velocity
            clean = bb.codec.decode(bb.schedule.predict_clean(z, v.float(), t_batch)).clamp(0, 1)
            psnr = peak_signal_noise_ratio(clean[:, 1:-1].flatten(0, 1), target, data_range=1.0,
                                           reduction="none", dim=(1, 2, 3))
            curve.append(float(psnr.mean()))
    return curve


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
