"""The label-free segment net: per-pixel embeddings at half resolution and the cluster prototypes
they are assigned to.

Trained on normal drives only (`umad train segmenter`, see `umad_common.training.train_segmenter`):
the cluster a pixel falls in must not change under photometric jitter and must move with the pixel
under crops, rescaling and flips, with clusters kept in use by balanced (Sinkhorn) assignments, as
in SwAV applied per pixel (PiCIE's invariance/equivariance idea with online prototypes instead of
per-epoch k-means). The `learned` segmenter (`umad_common.segmentation.learned`) turns the cluster
ids into connected segments.

The file format is NAME.safetensors plus NAME.json: `{"config": SegmentNetConfig, "training": {...}}`
(`umad_common.models.weights`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from umad_common.models.weights import WeightsError, load_model, save_weights


@dataclass
class SegmentNetConfig:
    widths: tuple[int, int] = (32, 64)  # channels at 1/2 and 1/4 of the input size
    embedding: int = 32  # per-pixel embedding size
    clusters: int = 24  # prototypes: the segment classes a pixel can take
    mean: tuple[float, float, float] = (0.5, 0.5, 0.5)  # input normalisation, RGB in [0, 1]
    std: tuple[float, float, float] = (0.25, 0.25, 0.25)

    @classmethod
    def from_dict(cls, data: dict, source: str = "config") -> SegmentNetConfig:
        """From a saved record's config (JSON lists back to tuples); WeightsError names the file."""
        try:
            cfg = cls(**{key: tuple(value) if isinstance(value, list) else value for key, value in data.items()})
        except TypeError as exc:
            raise WeightsError(f"{source}: not a segment net config ({exc})") from None
        if len(cfg.widths) != 2 or len(cfg.mean) != 3 or len(cfg.std) != 3 or cfg.clusters < 2:
            raise WeightsError(f"{source}: expected 2 widths, 3 mean/std values and >= 2 clusters, got {data}")
        return cfg

    def to_dict(self) -> dict:
        return asdict(self)


def conv(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    """3x3 conv, group norm, ReLU."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=dilation, dilation=dilation, bias=False),
        nn.GroupNorm(8, cout),
        nn.ReLU(inplace=True),
    )


class SegmentNet(nn.Module):
    """A two-level encoder (1/2 and 1/4, dilated convs for context at 1/4), the coarse level added
    back into the fine one, and a 1x1 projection to unit-length embeddings."""

    def __init__(self, config: SegmentNetConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = config or SegmentNetConfig()
        fine, coarse = cfg.widths
        self.fine = nn.Sequential(conv(3, fine, stride=2), conv(fine, fine))
        self.coarse = nn.Sequential(
            conv(fine, coarse, stride=2), conv(coarse, coarse, dilation=2), conv(coarse, coarse, dilation=4)
        )
        self.lateral = nn.Conv2d(coarse, fine, 1)
        self.merge = conv(fine, fine)
        self.project = nn.Conv2d(fine, cfg.embedding, 1)
        self.prototypes = nn.Parameter(F.normalize(torch.randn(cfg.clusters, cfg.embedding), dim=1))
        self.register_buffer("mean", torch.tensor(cfg.mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(cfg.std).view(1, 3, 1, 1), persistent=False)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [0, 1] -> (B, embedding, ⌈H/2⌉, ⌈W/2⌉) unit-length embeddings."""
        fine = self.fine((rgb - self.mean) / self.std)  # (B, w0, H/2, W/2)
        coarse = self.coarse(fine)  # (B, w1, H/4, W/4)
        up = F.interpolate(self.lateral(coarse), size=fine.shape[2:], mode="bilinear", align_corners=False)
        return F.normalize(self.project(self.merge(fine + up)), dim=1)

    def scores(self, embeddings: torch.Tensor) -> torch.Tensor:
        """Cosine similarity of (..., embedding) embeddings to each prototype: (..., clusters)."""
        return embeddings @ F.normalize(self.prototypes, dim=1).T

    @torch.inference_mode()
    def cluster_ids(self, rgb: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [0, 1] -> (B, H, W) int64: each pixel's nearest prototype, from the
        embeddings upsampled (bilinear) to the input size."""
        embeddings = F.interpolate(self(rgb), size=rgb.shape[2:], mode="bilinear", align_corners=False)
        return self.scores(embeddings.permute(0, 2, 3, 1)).argmax(dim=-1)


def save_segment_net(model: SegmentNet, path: str | Path, record: dict) -> Path:
    """Write NAME.safetensors and NAME.json (the config and the training record)."""
    return save_weights(model, path, model.config.to_dict(), record)


def load_segment_net(path: str | Path, device: str | torch.device = "cpu") -> tuple[SegmentNet, dict]:
    """A trained SegmentNet on `device` in eval mode and its JSON record; raises WeightsError naming
    the file, key and shapes."""
    return load_model(
        path, "segment net", lambda config, source: SegmentNet(SegmentNetConfig.from_dict(config, source)), device
    )
