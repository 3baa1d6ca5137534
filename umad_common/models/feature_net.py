"""The label-free perceptual feature net: a small VGG-shaped conv trunk with four feature levels.

It stands in for ImageNet VGG16 in Δ_PD when no VGG weights are supplied. Trained on normal drives
only (`umad train features`, see `umad_common.training.train_features`) with a dense VICReg
objective: features of two photometrically different views of the same frame (blur, noise, colour
jitter: the ways a world model's picture of a normal scene differs from the camera) must agree at
every pixel, while varying across pixels and frames and staying decorrelated across channels.

The file format is every model's (`umad_common/models/weights.py`): NAME.safetensors
(`features.N.weight`, ...) plus NAME.json, `{"config": FeatureNetConfig, "training": {...}}`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import nn

from umad_common.models.vgg16 import tapped_levels
from umad_common.models.weights import WeightsError, load_model, save_weights


@dataclass
class FeatureNetConfig:
    widths: tuple[int, int, int, int] = (16, 32, 64, 128)  # channels of the four levels (1, 1/2, 1/4, 1/8)
    mean: tuple[float, float, float] = (0.5, 0.5, 0.5)  # input normalisation, RGB in [0, 1]
    std: tuple[float, float, float] = (0.25, 0.25, 0.25)

    @classmethod
    def from_dict(cls, data: dict, source: str = "config") -> FeatureNetConfig:
        try:
            cfg = cls(**data)
        except TypeError as exc:
            raise WeightsError(f"{source}: not a feature net config ({exc})") from None
        cfg.widths = tuple(int(w) for w in cfg.widths)
        cfg.mean = tuple(float(v) for v in cfg.mean)
        cfg.std = tuple(float(v) for v in cfg.std)
        if len(cfg.widths) != 4 or len(cfg.mean) != 3 or len(cfg.std) != 3:
            raise WeightsError(f"{source}: expected 4 widths and 3 mean/std values, got {data}")
        return cfg

    def to_dict(self) -> dict:
        return asdict(self)


class FeatureNet(nn.Module):
    """Two 3x3 conv + ReLU per level, 2x2 max-pool between levels (VGG's pattern, 1/4 the width)."""

    def __init__(self, config: FeatureNetConfig | None = None) -> None:
        super().__init__()
        self.config = config or FeatureNetConfig()
        layers: list[nn.Module] = []
        self.taps: list[int] = []
        channels = 3
        for level, width in enumerate(self.config.widths):
            if level > 0:
                layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            for _ in range(2):
                layers += [nn.Conv2d(channels, width, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
                channels = width
            self.taps.append(len(layers) - 1)
        self.features = nn.Sequential(*layers)
        self.register_buffer("mean", torch.tensor(self.config.mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(self.config.std).view(1, 3, 1, 1), persistent=False)

    def forward(self, rgb: torch.Tensor) -> list[torch.Tensor]:
        """(B, 3, H, W) in [0, 1] -> four maps (B, widths[i], H/2^i, W/2^i), i = 0..3."""
        return tapped_levels(self.features, (rgb - self.mean) / self.std, self.taps)


def save_feature_net(model: FeatureNet, path: str | Path, record: dict | None = None) -> Path:
    """Write NAME.safetensors and NAME.json (the config and the training record)."""
    return save_weights(model, path, model.config.to_dict(), record)


def load_feature_net(path: str | Path, device: str | torch.device = "cpu") -> tuple[FeatureNet, dict]:
    """A trained FeatureNet on `device` in eval mode and its JSON record; raises WeightsError naming
    the file, key and shapes."""
    return load_model(
        path, "feature net", lambda config, source: FeatureNet(FeatureNetConfig.from_dict(config, source)), device
    )
