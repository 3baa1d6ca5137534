"""VGG16's convolutional trunk up to relu4_3, in plain torch, for the perceptual difference.

Layer indices match torchvision's `vgg16().features`, so a torchvision-format state dict file
(`features.0.weight`, `features.0.bias`, ... ; classifier and block-5 keys ignored) loads as is.
No weights ship with UMAD and nothing downloads: the user names a local file.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import torch
from torch import nn

from umad_common.models.weights import load_upstream_tensors

# torchvision's configuration "D" up to conv4_3; "M" is a 2x2 max-pool.
VGG16_TRUNK = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512)
# indices in `features` of relu1_2, relu2_2, relu3_3, relu4_3
VGG16_TAPS = {"relu1_2": 3, "relu2_2": 8, "relu3_3": 15, "relu4_3": 22}
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class Vgg16Features(nn.Module):
    """VGG16 `features[0..22]`; forward returns the four relu taps for an RGB batch in [0, 1]."""

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        channels = 3
        for item in VGG16_TRUNK:
            if item == "M":
                layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            else:
                layers += [nn.Conv2d(channels, int(item), kernel_size=3, padding=1), nn.ReLU(inplace=True)]
                channels = int(item)
        self.features = nn.Sequential(*layers)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, rgb: torch.Tensor) -> list[torch.Tensor]:
        """(B, 3, H, W) in [0, 1] -> [relu1_2 (B,64,H,W), relu2_2 (B,128,H/2,W/2),
        relu3_3 (B,256,H/4,W/4), relu4_3 (B,512,H/8,W/8)]."""
        return tapped_levels(self.features, (rgb - self.mean) / self.std, VGG16_TAPS.values())


def tapped_levels(features: nn.Sequential, x: torch.Tensor, taps: Iterable[int]) -> list[torch.Tensor]:
    """Run `x` through `features`, keeping the output of each layer whose index is in `taps`."""
    taps = set(taps)
    out = []
    for index, layer in enumerate(features):
        x = layer(x)
        if index in taps:
            out.append(x)
    return out


def load_vgg16_features(path: str | Path, device: str | torch.device = "cpu") -> tuple[Vgg16Features, dict]:
    """Vgg16Features with weights from a torchvision-format VGG16 state dict file, on `device` in eval
    mode, and its record: `{}`, an upstream file has none."""
    return load_upstream_tensors(Vgg16Features(), path, device).eval().requires_grad_(False), {}
