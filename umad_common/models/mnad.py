"""MNAD: memory-guided normality for anomaly detection (Park, Noh, Ham, CVPR 2020), reconstruction variant.

An encoder maps a frame to a grid of query features; each query reads a memory of M prototypical
normal items (attention over items) and the decoder reconstructs the frame from [query, read].
The memory is not trained by gradients: after each training step every item moves towards the
queries that chose it (`update_memory`). Two feature losses keep the memory discriminative:
compactness pulls each query to its nearest item, separateness (a triplet loss) pushes the second
nearest away. The anomaly map is the per-pixel squared L2 reconstruction error.

Deviations from the paper, kept small for 2 CPU cores: the encoder/decoder widths are the paper's
64/128/256 by default (configurable) but the step up to the 512-dim memory space is a single 3x3
convolution; the memory is frozen at inference (no test-time update), so the predictor is
stateless. Input: (B, 3, 128, 192) in [-1, 1]; output the same through tanh.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from umad_common.models.weights import config_from_dict, load_model, save_weights


@dataclass
class MnadConfig:
    height: int = 128  # model input height (frames are plainly resized, no crop)
    width: int = 192  # model input width
    widths: tuple[int, int, int] = (64, 128, 256)  # encoder channels per scale (the paper's)
    feature_dim: int = 512  # query / memory item dimension (paper: 512)
    memory_items: int = 10  # number of memory items M (paper: 10)
    compactness_weight: float = 0.1  # lambda_c of the paper
    separateness_weight: float = 0.1  # lambda_s of the paper
    separateness_margin: float = 1.0  # triplet margin of the separateness loss

    def __post_init__(self) -> None:
        self.widths = tuple(int(w) for w in self.widths)
        if len(self.widths) != 3 or min(self.widths) < 1:
            raise ValueError(f"MnadConfig.widths must be three positive channel counts, got {self.widths}")
        if self.height % 8 or self.width % 8:
            raise ValueError(f"MnadConfig size {self.height}x{self.width} must be divisible by 8 (three 2x poolings)")
        if self.memory_items < 2:
            raise ValueError(
                f"MnadConfig.memory_items must be >= 2 (separateness needs two items), got {self.memory_items}"
            )

    def to_dict(self) -> dict:
        d = asdict(self)
        d["widths"] = list(self.widths)
        return d

    @classmethod
    def from_dict(cls, data: dict) -> MnadConfig:
        return config_from_dict(cls, data, "MNAD")


class MnadOutput(NamedTuple):
    recon: torch.Tensor  # (B, 3, H, W) in [-1, 1]
    query: torch.Tensor  # (B*h*w, D) L2-normalised encoder features
    compactness: torch.Tensor  # scalar: mean squared distance of each query to its nearest item
    separateness: torch.Tensor  # scalar: triplet loss (nearest item positive, second nearest negative)


def conv_block(c_in: int, c_out: int, last_relu: bool = True) -> nn.Sequential:
    """Two 3x3 conv + batch norm (+ ReLU) layers, MNAD's `Basic` block."""
    layers: list[nn.Module] = [
        nn.Conv2d(c_in, c_out, 3, padding=1),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
        nn.Conv2d(c_out, c_out, 3, padding=1),
        nn.BatchNorm2d(c_out),
    ]
    if last_relu:
        layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


def up_block(c_in: int, c_out: int) -> nn.Sequential:
    """2x transposed-conv upsampling, MNAD's `Upsample` block."""
    return nn.Sequential(
        nn.ConvTranspose2d(c_in, c_out, 3, stride=2, padding=1, output_padding=1),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class Encoder(nn.Module):
    def __init__(self, cfg: MnadConfig):
        super().__init__()
        w1, w2, w3 = cfg.widths
        self.block1 = conv_block(3, w1)
        self.block2 = conv_block(w1, w2)
        self.block3 = conv_block(w2, w3)
        self.to_feature = nn.Conv2d(w3, cfg.feature_dim, 3, padding=1)  # no ReLU: queries may be negative

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, 3, H, W) -> (B, D, H/8, W/8)
        x = F.max_pool2d(self.block1(x), 2)
        x = F.max_pool2d(self.block2(x), 2)
        x = F.max_pool2d(self.block3(x), 2)
        return self.to_feature(x)


class Decoder(nn.Module):
    """No skip connections: the reconstruction must pass through the memory read."""

    def __init__(self, cfg: MnadConfig):
        super().__init__()
        w1, w2, w3 = cfg.widths
        self.from_feature = nn.Sequential(
            nn.Conv2d(2 * cfg.feature_dim, w3, 1), nn.BatchNorm2d(w3), nn.ReLU(inplace=True)
        )
        self.up3, self.block3 = up_block(w3, w3), conv_block(w3, w2)
        self.up2, self.block2 = up_block(w2, w2), conv_block(w2, w1)
        self.up1, self.block1 = up_block(w1, w1), conv_block(w1, w1)
        self.to_image = nn.Conv2d(w1, 3, 3, padding=1)

    def forward(self, z: torch.Tensor) -> torch.Tensor:  # (B, 2D, h, w) -> (B, 3, 8h, 8w)
        x = self.from_feature(z)
        x = self.block3(self.up3(x))
        x = self.block2(self.up2(x))
        x = self.block1(self.up1(x))
        return torch.tanh(self.to_image(x))


class Mnad(nn.Module):
    """Encoder -> memory read -> decoder; `update_memory` is the training-time memory update."""

    def __init__(self, cfg: MnadConfig | None = None):
        super().__init__()
        self.cfg = cfg or MnadConfig()
        self.encoder = Encoder(self.cfg)
        self.decoder = Decoder(self.cfg)
        self.register_buffer("memory", F.normalize(torch.rand(self.cfg.memory_items, self.cfg.feature_dim), dim=1))

    def forward(self, x: torch.Tensor) -> MnadOutput:
        b, _, h, w = x.shape
        if (h, w) != (self.cfg.height, self.cfg.width):
            raise ValueError(f"Mnad expects input (B, 3, {self.cfg.height}, {self.cfg.width}), got {tuple(x.shape)}")
        feature = F.normalize(self.encoder(x), dim=1)  # (B, D, h', w')
        d, hf, wf = feature.shape[1:]
        query = feature.permute(0, 2, 3, 1).reshape(-1, d)  # (B*h'*w', D)
        score = query @ self.memory.t()  # (N, M)
        read = torch.softmax(score, dim=1) @ self.memory  # (N, D)
        top2 = torch.topk(score, 2, dim=1).indices
        nearest, second = self.memory[top2[:, 0]], self.memory[top2[:, 1]]
        compactness = F.mse_loss(query, nearest)
        separateness = F.triplet_margin_loss(query, nearest, second, margin=self.cfg.separateness_margin)
        z = torch.cat([query, read], dim=1).reshape(b, hf, wf, 2 * d).permute(0, 3, 1, 2)
        return MnadOutput(self.decoder(z), query, compactness, separateness)

    def loss(self, x: torch.Tensor, out: MnadOutput) -> tuple[torch.Tensor, dict[str, float]]:
        """Reconstruction MSE + lambda_c compactness + lambda_s separateness; parts for logging."""
        reconstruction = F.mse_loss(out.recon, x)
        total = (
            reconstruction
            + self.cfg.compactness_weight * out.compactness
            + self.cfg.separateness_weight * out.separateness
        )
        parts = {
            "reconstruction": float(reconstruction.detach()),
            "compactness": float(out.compactness.detach()),
            "separateness": float(out.separateness.detach()),
        }
        return total, parts

    @torch.no_grad()
    def update_memory(self, query: torch.Tensor) -> None:
        """Move each item towards the queries whose nearest item it is, weighted by their
        attention to it (normalised by its strongest query), then re-normalise (paper eq. 4)."""
        query = query.detach()
        score = query @ self.memory.t()  # (N, M)
        weight = torch.softmax(score, dim=0)  # over queries, per item
        nearest = score.argmax(dim=1)  # (N,)
        chosen = F.one_hot(nearest, self.cfg.memory_items).to(query.dtype)  # (N, M)
        strongest = weight.max(dim=0).values.clamp_min(1e-12)  # (M,)
        delta = ((chosen * weight) / strongest).t() @ query  # (M, D)
        self.memory.copy_(F.normalize(self.memory + delta, dim=1))

    @torch.no_grad()
    def anomaly_map(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [-1, 1] -> (B, H, W) per-pixel squared L2 error over the colour channels."""
        out = self.forward(x)
        return ((out.recon - x) ** 2).sum(dim=1)


def to_input(rgb: np.ndarray, cfg: MnadConfig) -> torch.Tensor:
    """(H, W, 3) uint8 camera image -> (1, 3, h, w) float32 in [-1, 1] at the model size (plain resize)."""
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"MNAD input: expected an (H, W, 3) uint8 RGB image, got {rgb.dtype} {rgb.shape}")
    if rgb.shape[:2] != (cfg.height, cfg.width):
        rgb = cv2.resize(rgb, (cfg.width, cfg.height), interpolation=cv2.INTER_AREA)
    x = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float() / 127.5 - 1.0
    return x.unsqueeze(0)


def save_mnad(model: Mnad, path: str | Path, record: dict | None = None) -> Path:
    """Write the weights and memory (safetensors) and a JSON beside them: config + `record`."""
    return save_weights(model, path, model.cfg.to_dict(), record)


def load_mnad(path: str | Path, device: str | torch.device = "cpu") -> tuple[Mnad, dict]:
    """Load NAME.safetensors + NAME.json; returns the model on `device` in eval mode and the JSON record."""
    return load_model(path, "MNAD", lambda config, _: Mnad(MnadConfig.from_dict(config)), device)
