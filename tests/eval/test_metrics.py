"""PSNR/SSIM agree with scikit-image; LPIPS reports n/a with a reason; protocol averaging order."""

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from tracegs.eval.metrics import ImageMetrics, gsfixer_ssim, lpips_availability, mean_metrics, png_bytes


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


def test_both_ssims_are_reported_the_headline_under_its_convention():
    """``ssim`` follows ``ssim_convention`` and ``ssim_alt`` holds the other: GSFixer's (8-bit PNGs, 3DGS's SSIM,
    checked against its own function in test_gsfixer_goldens) or torchmetrics' on the float images, unchanged."""
    pred, gt = _random_pair(5)
    float_ssim = ImageMetrics(lpips=False).per_view(pred, gt)[0]["ssim"]
    png_ssim = gsfixer_ssim(png_bytes(pred), png_bytes(gt)).item()
    assert abs(float_ssim - png_ssim) > 1e-4  # two metrics: a table must say which
    default = ImageMetrics(lpips=False)
    assert (default.per_view(pred, gt)[0]["ssim"], default.per_view(pred, gt)[0]["ssim_alt"]) == (float_ssim, png_ssim)
    gsfixer = ImageMetrics(lpips=False, ssim_convention="gsfixer")
    assert (gsfixer.per_view(pred, gt)[0]["ssim"], gsfixer.per_view(pred, gt)[0]["ssim_alt"]) == (png_ssim, float_ssim)
    assert gsfixer.ssim_label.startswith("SSIM of 8-bit PNG images") and "SSIM′" in gsfixer.ssim_label
    with pytest.raises(ValueError, match="ssim_convention"):
        ImageMetrics(lpips=False, ssim_convention="8bit")


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
