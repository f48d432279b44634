"""Image-quality metrics of the evaluation protocol (supplement B, "Metric computation").

PSNR comes from torchmetrics at data range 1 (images in [0, 1]). SSIM is reported twice, under both conventions
in use (``SSIM_CONVENTIONS``): the headline column ``ssim`` under ``evaluation.ssim_convention``, the second,
``ssim_alt``, under the other one. LPIPS is LPIPS-VGG (``tracegs.eval.lpips_vgg``: torchmetrics'
heads on a VGG16 trunk read from torchvision's ImageNet weights file, ``evaluation.lpips_weights``, by default
where the torch hub cache keeps it); without that file LPIPS is reported as unavailable with the reason,
never as a made-up number, unless the experiment requires it (``evaluation.require_lpips``), in which case
the run stops before any work.

Averaging follows the paper: each metric is averaged over a scene's test views first, then the
unweighted mean is taken over scenes. Reference (captured) frames are not test views and must not be
passed in.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from tracegs.errors import ConfigError
from tracegs.eval.lpips_vgg import LpipsVgg

HEADLINE_METRICS = ("psnr", "ssim", "lpips")  # the paper's three (Table 3's columns)
# Tables 1/2 add ``ssim_alt``, the same SSIM under the convention the headline column does not use; it comes last
# so the headline columns keep their places.
METRIC_NAMES = (*HEADLINE_METRICS, "ssim_alt")
VGG16_WEIGHTS_FILE = "vgg16-397923af.pth"

# Both LPIPS conventions in use. The official 3DGS evaluation feeds [0, 1] images straight into an
# LPIPS network that expects [-1, 1] (its lpipsPyTorch does no rescaling); in torchmetrics that is
# normalize=False with unscaled [0, 1] inputs. The LPIPS authors' convention maps [0, 1] to [-1, 1]
# first (torchmetrics normalize=True). The two give different numbers, so every table names its own.
LPIPS_CONVENTIONS = {
    "3dgs": "LPIPS-VGG (unscaled [0,1] images, as the official 3DGS metrics.py; torchmetrics normalize=False)",
    "standard": "LPIPS-VGG ([0,1] images mapped to [-1,1]; torchmetrics normalize=True)",
}


# Both SSIM conventions in use. GSFixer's metrics.py (l. 25-35, 74) scores the 8-bit PNGs the render script wrote
# with 3DGS's SSIM (utils/loss_utils.py: Gaussian window, zero padding); torchmetrics' SSIM on float images pads
# by reflection and crops the border. The two give different numbers, so every table names both.
SSIM_CONVENTIONS = {
    "gsfixer": "SSIM of 8-bit PNG images (3DGS's 11x11 Gaussian window, zero padding, as GSFixer's metrics.py)",
    "torchmetrics": "SSIM of float [0,1] images (torchmetrics, 11x11 Gaussian window, sigma 1.5)",
}


def require_ssim_convention(convention: str, field: str) -> None:
    """A one-line error naming ``field`` unless ``convention`` is a key of ``SSIM_CONVENTIONS``."""
    if convention not in SSIM_CONVENTIONS:
        raise ValueError(f"{field} must be one of {sorted(SSIM_CONVENTIONS)}, got {convention!r}")


def ssim_label(convention: str) -> str:
    """The SSIM columns' caption for tables: the headline's convention, then the second column's."""
    (other,) = set(SSIM_CONVENTIONS) - {convention}
    return f"{SSIM_CONVENTIONS[convention]}, second column (SSIM′): {SSIM_CONVENTIONS[other]}"


def require_lpips_convention(convention: str, field: str) -> None:
    """A one-line error naming ``field`` unless ``convention`` is a key of ``LPIPS_CONVENTIONS`` (the names are
    not identifiers, e.g. "3dgs", so they cannot be an Enum that OmegaConf checks at composition)."""
    if convention not in LPIPS_CONVENTIONS:
        raise ValueError(f"{field} must be one of {sorted(LPIPS_CONVENTIONS)}, got {convention!r}")


@dataclass(frozen=True)
class LpipsAvailability:
    """Whether LPIPS-VGG can be computed here, and if not, why."""

    available: bool
    reason: str = ""


def vgg16_weights_path() -> Path:
    """Where torchvision looks for the VGG16 ImageNet weights (``$TORCH_HOME/hub/checkpoints``)."""
    return Path(torch.hub.get_dir()) / "checkpoints" / VGG16_WEIGHTS_FILE


def lpips_weights_file(weights: str | None) -> Path:
    """The VGG16 weights LPIPS reads: ``weights`` (evaluation.lpips_weights), else the torch hub cache's copy."""
    return Path(weights) if weights is not None else vgg16_weights_path()


def lpips_availability(weights: str | None = None) -> LpipsAvailability:
    """Whether LPIPS-VGG can be computed, without downloading anything: its VGG16 weights file must exist."""
    path = lpips_weights_file(weights)
    if not path.is_file():
        return LpipsAvailability(False, f"VGG16 ImageNet weights not found at {path}")
    return LpipsAvailability(True)


def require_lpips(enabled: bool, required: bool, weights: str | None) -> None:
    """Stop before any work when the experiment requires LPIPS (its tables report it) and it cannot be computed."""
    if not required:
        return
    if not enabled:
        raise ConfigError("evaluation.lpips", "false, but this experiment requires LPIPS (evaluation.require_lpips)")
    status = lpips_availability(weights)
    if not status.available:
        raise ConfigError("evaluation.lpips_weights", f"{status.reason}; this experiment requires LPIPS "
                                                      "(evaluation.require_lpips): put torchvision's VGG16 ImageNet "
                                                      "weights (vgg16-397923af.pth) there")


def png_bytes(image: Tensor) -> Tensor:
    """A [0, 1] image as the 8-bit PNG the 3DGS render script writes (``torchvision.utils.save_image``: x 255,
    + 0.5, clamped, truncated to uint8). GSFixer's release scores such files (metrics.py l. 25-35) and ships no
    writer of its own, so 3DGS's, whose metrics.py it is, stands in."""
    return image.mul(255).add(0.5).clamp(0, 255).to(torch.uint8)


def gsfixer_ssim(pred: Tensor, target: Tensor) -> Tensor:
    """SSIM of two 8-bit images [3,H,W] (uint8) as GSFixer's metrics.py computes it (l. 32-33 and 74, its
    utils/loss_utils.py l. 26-105, 3DGS's): both read back as uint8 / 255 in float32, an 11 x 11 Gaussian window
    of sigma 1.5 with zero padding at the borders, the map averaged over pixels and channels."""
    a, b = (image.float()[None] / 255 for image in (pred, target))
    taps = torch.exp(-((torch.arange(11, dtype=torch.float32) - 5) ** 2) / (2 * 1.5**2))
    taps = taps / taps.sum()
    window = (taps[:, None] @ taps[None, :]).expand(a.shape[1], 1, 11, 11)

    def blur(x: Tensor) -> Tensor:
        return torch.nn.functional.conv2d(x, window, padding=5, groups=a.shape[1])

    mean_a, mean_b = blur(a), blur(b)
    var_a, var_b = blur(a * a) - mean_a**2, blur(b * b) - mean_b**2
    covariance = blur(a * b) - mean_a * mean_b
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mean_a * mean_b + c1) * (2 * covariance + c2))
            / ((mean_a**2 + mean_b**2 + c1) * (var_a + var_b + c2))).mean()


def _as_batch(image: Tensor, name: str) -> Tensor:
    if image.dim() == 3:
        image = image.unsqueeze(0)
    if image.dim() != 4 or image.shape[1] != 3:
        raise ValueError(f"{name} must have shape [3,H,W] or [B,3,H,W], got {tuple(image.shape)}")
    return image.float()


class ImageMetrics:
    """Runtime evaluator of PSNR / SSIM / LPIPS between renders and ground truth, both in [0, 1]."""

    def __init__(self, lpips: bool = True, lpips_convention: str = "3dgs", device: str | torch.device = "cpu",
                 lpips_weights: str | None = None, ssim_convention: str = "torchmetrics"):
        require_lpips_convention(lpips_convention, "lpips_convention")
        require_ssim_convention(ssim_convention, "ssim_convention")
        self.lpips_convention = lpips_convention
        self.ssim_convention = ssim_convention
        self.lpips_status = (lpips_availability(lpips_weights) if lpips
                             else LpipsAvailability(False, "disabled by config"))
        self._lpips = None
        if self.lpips_status.available:
            self._lpips = LpipsVgg(lpips_weights_file(lpips_weights)).to(device)

    @property
    def lpips_label(self) -> str:
        """The LPIPS column caption for tables: the convention, or ``n/a`` with the reason."""
        if self.lpips_status.available:
            return LPIPS_CONVENTIONS[self.lpips_convention]
        return f"LPIPS n/a: {self.lpips_status.reason}"

    @property
    def ssim_label(self) -> str:
        return ssim_label(self.ssim_convention)

    @torch.no_grad()
    def per_view(self, pred: Tensor | Sequence[Tensor], target: Tensor | Sequence[Tensor]) -> list[dict[str, float | None]]:
        """Metrics of each image of the batch (``[3,H,W]``, ``[B,3,H,W]`` or a list of ``[3,H,W]`` views, which
        may differ in size from view to view), one dict per view."""
        if isinstance(pred, Tensor) and isinstance(target, Tensor):
            pred, target = _as_batch(pred, "pred").split(1), _as_batch(target, "target").split(1)
        if len(pred) != len(target):
            raise ValueError(f"{len(pred)} predicted views for {len(target)} targets")
        results = []
        for p, t in zip(pred, target):
            p, t = _as_batch(p, "pred").clamp(0.0, 1.0), _as_batch(t, "target").clamp(0.0, 1.0)
            if p.shape != t.shape:
                raise ValueError(f"pred {tuple(p.shape)} and target {tuple(t.shape)} differ in shape")
            psnr = peak_signal_noise_ratio(p, t, data_range=1.0).item()
            ssim = {"torchmetrics": structural_similarity_index_measure(p, t, data_range=1.0).item(),
                    "gsfixer": gsfixer_ssim(png_bytes(p[0]), png_bytes(t[0])).item()}
            lpips = None
            if self._lpips is not None:
                device = self._lpips.scaling_layer.shift.device
                lpips = self._lpips(p.to(device), t.to(device), normalize=self.lpips_convention == "standard").item()
            (other,) = set(ssim) - {self.ssim_convention}
            results.append({"psnr": psnr, "ssim": ssim[self.ssim_convention], "lpips": lpips,
                            "ssim_alt": ssim[other]})
        return results


def mean_metrics(rows: Sequence[Mapping[str, float | None]]) -> dict[str, float | None]:
    """Unweighted mean of each metric over ``rows``; ``None`` when any row lacks that metric.

    Used twice, as the protocol prescribes: over a scene's test views, then over the scene means.
    """
    if not rows:
        raise ValueError("cannot average metrics over an empty list of views/scenes")
    means: dict[str, float | None] = {}
    for name in METRIC_NAMES:
        values = [row.get(name) for row in rows]
        if any(v is None or (isinstance(v, float) and math.isnan(v)) for v in values):
            means[name] = None
        else:
            means[name] = float(sum(values) / len(values))
    return means
