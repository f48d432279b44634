"""Fig. 6 per-step curve: one value per reverse step, ending at the restorer's actual output."""

import pytest
import torch
from torchmetrics.functional.image import peak_signal_noise_ratio

from tracegs.eval.per_step import mean_curves, per_step_psnr
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig
from tracegs.restorer.sampler import RestorationPipeline


def test_per_step_curve_ends_at_the_restored_output():
    pipeline = RestorationPipeline(build_backbone(BackboneConfig()))
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(1, 9, 3, 24, 32, generator=g)
    frames = (gt + 0.1 * torch.randn(gt.shape, generator=g)).clamp(0, 1)
    refs = gt[:, [0, -1]]
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
