"""LPIPS-VGG (supplement B) from a local VGG16 weights file, without torchvision.

torchmetrics' LPIPS builds its VGG16 trunk through torchvision, and no torchvision release works with the torch
this project pins on CPU machines (installing one pulls another torch), so LPIPS would be missing exactly where
the tables are rehearsed. The trunk is thirteen 3x3 convolutions; it is written here in torchvision's
``vgg16().features`` layout, so torchvision's released ImageNet file (``vgg16-397923af.pth``, the one the torch
hub cache holds) loads into it key for key. Everything else is torchmetrics': its input ``ScalingLayer``, its
``NetLinLayer`` heads and the linear weights it ships (``lpips_models/vgg.pth``, the LPIPS authors' v0.1). The
distance is theirs: per tapped layer, features normalised over channels, squared difference, the 1x1 head,
the spatial mean; summed over the five taps (relu1_2, relu2_2, relu3_3, relu4_3, relu5_3).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn
from torchmetrics.functional.image import lpips as torchmetrics_lpips

from tracegs.errors import InputFileError

# torchvision's vgg16 "D" configuration: output channels of each 3x3 convolution, "M" a 2x2 max-pool.
VGG16_LAYERS = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
# Indices in ``features`` after which LPIPS taps the trunk (the ReLUs of relu1_2 ... relu5_3).
LPIPS_TAPS = (3, 8, 15, 22, 29)
TAP_CHANNELS = (64, 128, 256, 512, 512)
HEADS_FILE = Path(torchmetrics_lpips.__file__).parent / "lpips_models" / "vgg.pth"


def vgg16_features() -> nn.Sequential:
    """VGG16's convolutional trunk up to relu5_3, indexed as torchvision's ``vgg16().features``."""
    layers: list[nn.Module] = []
    channels = 3
    for width in VGG16_LAYERS:
        if width == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(channels, width, kernel_size=3, padding=1), nn.ReLU(inplace=False)]
            channels = width
    return nn.Sequential(*layers)


def read_vgg16_features(path: str | Path, field: str, expected: dict[str, Tensor]) -> dict[str, Tensor]:
    """The ``features.*`` tensors of a torchvision VGG16 state-dict file (the classifier's are not used), checked
    key for key and shape for shape against ``expected`` (the trunk's state dict)."""
    path = Path(path)
    fix = f"point {field} at torchvision's VGG16 ImageNet weights (vgg16-397923af.pth)"
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError as error:
        raise InputFileError(path, "no such file", fix) from error
    except Exception as error:  # noqa: BLE001 - any unreadable file gets the same one-line answer
        raise InputFileError(path, f"not a loadable state dict ({type(error).__name__}: {error})", fix) from error
    if not isinstance(state, dict):
        raise InputFileError(path, f"holds a {type(state).__name__}, not a state dict", fix)
    features = {key.removeprefix("features."): value for key, value in state.items() if key.startswith("features.")}
    extra = sorted(set(features) - set(expected))
    if extra:
        raise InputFileError(path, f"not VGG16's features: 'features.{extra[0]}' is not in VGG16's trunk", fix)
    for key, value in expected.items():
        if key not in features or features[key].shape != value.shape:
            found = tuple(features[key].shape) if key in features else "missing"
            raise InputFileError(path, f"not VGG16's features: 'features.{key}' is {found}, VGG16 has "
                                       f"{tuple(value.shape)}", fix)
    return features


class LpipsVgg(nn.Module):
    """LPIPS-VGG distance between image batches; ``normalize`` maps [0, 1] inputs to [-1, 1] first."""

    def __init__(self, vgg16_weights: str | Path, field: str = "evaluation.lpips_weights"):
        super().__init__()
        self.scaling_layer = torchmetrics_lpips.ScalingLayer()
        self.features = vgg16_features()
        self.features.load_state_dict(read_vgg16_features(vgg16_weights, field, self.features.state_dict()))
        self.heads = nn.ModuleList(torchmetrics_lpips.NetLinLayer(c, use_dropout=True) for c in TAP_CHANNELS)
        heads = torch.load(HEADS_FILE, map_location="cpu", weights_only=True)
        for index, head in enumerate(self.heads):
            head.load_state_dict({k.removeprefix(f"lin{index}."): v for k, v in heads.items()
                                  if k.startswith(f"lin{index}.")})
        self.eval().requires_grad_(False)

    def taps(self, images: Tensor) -> list[Tensor]:
        """Channel-normalised activations at the five LPIPS taps."""
        out, x = [], self.scaling_layer(images)
        for index, layer in enumerate(self.features):
            x = layer(x)
            if index in LPIPS_TAPS:
                out.append(x / (x.square().sum(dim=1, keepdim=True) + 1e-8).sqrt())  # eps as torchmetrics
        return out

    @torch.no_grad()
    def forward(self, images: Tensor, targets: Tensor, normalize: bool = False) -> Tensor:
        if normalize:
            images, targets = 2 * images - 1, 2 * targets - 1
        distance = images.new_zeros(images.shape[0])
        for head, a, b in zip(self.heads, self.taps(images), self.taps(targets)):
            distance = distance + head((a - b).square()).mean(dim=(1, 2, 3))
        return distance
