"""The label-free perceptual feature net: a small VGG-shaped conv trunk with four feature levels.

It stands in for ImageNet VGG16 in Δ_PD when no VGG weights are supplied. Trained on normal drives
only (`umad train features`, see `umad_common.training.train_features`) with a dense VICReg
objective: features of two photometrically different views of the same frame (blur, noise, colour
jitter: the ways a world model's picture of a normal scene differs from the camera) must agree at
every pixel, while varying across pixels and frames and staying decorrelated across channels.

The file format is safetensors (`features.N.weight`, ...) plus a JSON config next to it
(`<file>.json`) holding `FeatureNetConfig`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch import nn

from umad_common.models.vgg16 import load_into, read_state_dict
from umad_common.models.weights import WeightsError


@dataclass
class FeatureNetConfig:
    widths: tuple[int, int, int, int] = (16, 32, 64, 128)  # channels of the four levels (1, 1/2, 1/4, 1/8)
    mean: tuple[float, float, float] = (0.5, 0.5, 0.5)  # input normalisation, RGB in [0, 1]
    std: tuple[float, float, float] = (0.25, 0.25, 0.25)
    training: dict = field(default_factory=dict)  # how the file was made (data, epochs, seed, loss)

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
        x = (rgb - self.mean) / self.std
        taps = set(self.taps)
        out = []
        for index, layer in enumerate(self.features):
            x = layer(x)
            if index in taps:
                out.append(x)
        return out


def config_path(weights: Path) -> Path:
    """Where the JSON config of a weight file lives: `<file>.json` beside `<file>.safetensors`."""
    return weights.with_suffix(".json")


def save_feature_net(model: FeatureNet, path: str | Path) -> None:
    """Write `path` (safetensors) and its JSON config."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file({k: v.detach().contiguous() for k, v in model.state_dict().items()}, str(path))
    config_path(path).write_text(json.dumps(asdict(model.config), indent=2) + "\n")


def load_feature_net(path: str | Path) -> FeatureNet:
    """A trained FeatureNet in eval mode; raises WeightsError naming the file, key and shapes."""
    path = Path(path)
    cfg_file = config_path(path)
    if not cfg_file.is_file():
        raise WeightsError(f"{cfg_file}: feature net config not found (expected beside {path.name})")
    try:
        data = json.loads(cfg_file.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise WeightsError(f"{cfg_file}: cannot read feature net config ({exc})") from None
    model = FeatureNet(FeatureNetConfig.from_dict(data, str(cfg_file)))
    load_into(model, read_state_dict(path), path)
    return model.eval().requires_grad_(False)
