"""PSNR/SSIM agree with scikit-image; LPIPS reports n/a with a reason; protocol averaging order."""

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from tracegs.eval.metrics import ImageMetrics, lpips_availability, mean_metrics


def _random_pair(seed: int, h: int = 48, w: int = 72):
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(3, h, w, generator=g)
    pred = (gt + 0.15 * torch.randn(3, h, w, generator=g)).clamp(0, 1)
    return pred, gt


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_psnr_ssim_agree_with_scikit_image(seed):
    """Independent implementation: skimage.metrics.peak_signal_noise_ratio (data_range=1) and
    skimage.metrics.structural_similarity with gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1, channel_axis=-1 (Wang et al.'s Gaussian-window SSIM).

    The two SSIMs differ only at the image border (torchmetrics averages the whole reflect-padded map,
    scikit-image crops a 5-pixel border), so the images are large enough for that to stay below 5e-4."""
    pred, gt = _random_pair(seed, 128, 192)
    ours = ImageMetrics(lpips=False).per_view(pred, gt)[0]
    p = pred.permute(1, 2, 0).double().numpy()
    t = gt.permute(1, 2, 0).double().numpy()
    ref_psnr = peak_signal_noise_ratio(t, p, data_range=1.0)
    ref_ssim = structural_similarity(
        t, p, data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False
    )
    assert ours["psnr"] == pytest.approx(ref_psnr, abs=1e-3)
    assert ours["ssim"] == pytest.approx(ref_ssim, abs=5e-4)


def test_identical_images_give_perfect_ssim_and_degrading_noise_lowers_both():
    pred, gt = _random_pair(3)
    metrics = ImageMetrics(lpips=False)
    same = metrics.per_view(gt, gt)[0]
    assert same["ssim"] == pytest.approx(1.0, abs=1e-5)
    worse = (gt + 0.4 * (pred - gt)).clamp(0, 1)
    mild, strong = metrics.per_view(torch.stack([worse, pred]), torch.stack([gt, gt]))
    assert mild["psnr"] > strong["psnr"] and mild["ssim"] > strong["ssim"]


def test_lpips_reports_unavailable_with_reason_when_weights_are_missing(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    status = lpips_availability()
    assert not status.available
    assert str(tmp_path) in status.reason
    metrics = ImageMetrics(lpips=True)
    pred, gt = _random_pair(4)
    assert metrics.per_view(pred, gt)[0]["lpips"] is None
    assert metrics.lpips_label.startswith("LPIPS n/a: ")


def test_mean_is_over_views_then_over_scenes():
    scene_a = [{"psnr": 10.0, "ssim": 0.1, "lpips": None}] * 3
    scene_b = [{"psnr": 20.0, "ssim": 0.5, "lpips": None}]
    per_scene = [mean_metrics(scene_a), mean_metrics(scene_b)]
    overall = mean_metrics(per_scene)
    assert overall["psnr"] == pytest.approx(15.0)  # pooled views would give 12.5
    assert overall["ssim"] == pytest.approx(0.3)
    assert overall["lpips"] is None


def test_shape_mismatch_is_rejected():
    with pytest.raises(ValueError, match="differ in shape"):
        ImageMetrics(lpips=False).per_view(torch.rand(3, 8, 8), torch.rand(3, 8, 9))
    with pytest.raises(ValueError, match="empty"):
        mean_metrics([])
    assert np.isfinite(ImageMetrics(lpips=False).per_view(torch.rand(3, 16, 16), torch.rand(3, 16, 16))[0]["psnr"])
