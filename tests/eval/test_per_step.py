"""Fig. 6 per-step curve: one value per reverse step, ending at the restorer's actual output."""

import pytest
import torch
from torchmetrics.functional.image import peak_signal_noise_ratio

from tracegs.eval.per_step import mean_curves, per_step_psnr
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig
from tracegs.restorer.sampler import RestorationPipeline


def noisy_clip(num_frames: int):
    """A random restorer, a ground-truth clip [1,F,3,24,32], its noisy rendering and the end frames as references."""
    pipeline = RestorationPipeline(build_backbone(BackboneConfig()))
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(1, num_frames, 3, 24, 32, generator=g)
    frames = (gt + 0.1 * torch.randn(gt.shape, generator=g)).clamp(0, 1)
    return pipeline, gt, frames, gt[:, [0, -1]]


def test_per_step_curve_ends_at_the_restored_output():
    pipeline, gt, frames, refs = noisy_clip(9)
    curve = per_step_psnr(pipeline, frames, refs, ["a scene"], gt, seed=5, steps=3)
    assert len(curve) == 3
    # rectified flow: the x0 predicted at the last state is exactly the solver's final step
    restored = pipeline.restore(frames, refs, ["a scene"], seed=5, steps=3).clamp(0, 1)
    final = peak_signal_noise_ratio(restored[0, 1:-1], gt[0, 1:-1], data_range=1.0, reduction="none",
                                    dim=(1, 2, 3)).mean()
    assert curve[-1] == pytest.approx(float(final), abs=1e-3)


def test_mean_curves_average_label_by_label():
    mean = mean_curves([{"F": [1.0, 3.0], "E": [0.0, 1.0]}, {"F": [3.0, 5.0], "E": [2.0, 1.0]}])
    assert mean == {"F": [2.0, 4.0], "E": [1.0, 1.0]}


def test_per_step_curve_is_the_weighted_mean_of_its_frames_curves():
    """Held-out clips weigh each distinct ground-truth frame once (tracegs/eval/clips.py): the weighted curve is the
    weighted mean of the single frames' curves."""
    pipeline, gt, frames, refs = noisy_clip(5)
    weights = torch.tensor([0.25, 0.25, 0.5], dtype=torch.float64)

    def curve(w):
        return per_step_psnr(pipeline, frames, refs, ["a scene"], gt, seed=5, steps=2, frame_weights=w)

    single = [curve(torch.eye(3, dtype=torch.float64)[j]) for j in range(3)]
    expected = [sum(float(weights[j]) * single[j][step] for j in range(3)) for step in range(2)]
    assert curve(weights) == pytest.approx(expected, abs=1e-4)
