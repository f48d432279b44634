"""torchvision's VGG16 ImageNet weights file (``vgg16-397923af.pth``) as the torch hub cache holds it: a
``torch.save``d state dict keyed ``features.<index>.{weight,bias}`` (torchvision.models.vgg, configuration "D":
13 3x3 convolutions, ReLU after each, max-pool at indices 4, 9, 16, 23, 30) and ``classifier.*``.

Written from this table alone, never from our module, with random values at torchvision's initialisation
(Kaiming normal, fan-out, ReLU; zero bias), so a layout drift on our side fails to load it. The classifier is a
small stand-in: LPIPS never reads it, and the real one holds 120 M parameters.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

# index in ``features`` -> (out channels, in channels) of each 3x3 convolution
VGG16_CONVOLUTIONS = {0: (64, 3), 2: (64, 64), 5: (128, 64), 7: (128, 128), 10: (256, 128), 12: (256, 256),
                      14: (256, 256), 17: (512, 256), 19: (512, 512), 21: (512, 512), 24: (512, 512),
                      26: (512, 512), 28: (512, 512)}


def write_vgg16_weights(path: Path, seed: int = 0) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    state = {}
    for index, (out_channels, in_channels) in VGG16_CONVOLUTIONS.items():
        std = math.sqrt(2.0 / (out_channels * 9))
        state[f"features.{index}.weight"] = torch.randn(out_channels, in_channels, 3, 3, generator=generator) * std
        state[f"features.{index}.bias"] = torch.zeros(out_channels)
    state["classifier.6.weight"] = torch.randn(10, 16, generator=generator)
    state["classifier.6.bias"] = torch.zeros(10)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(state, path)
    return state
