"""Δ_PD, the perceptual difference: disagreement of deep features instead of pixels."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from umad_common.differences.metrics import DifferenceInputError, DifferenceMetric, MetricOptions
from umad_common.models.device import resolve_device


class PerceptualDifference(DifferenceMetric):
    """Δ_PD = Σ over feature levels l of upsample(mean over channels |F^l(x) - F^l(x̂_t)|).

    The extractor returns a list of (1, C_l, h_l, w_l) maps: ImageNet VGG16 at relu1_2, relu2_2,
    relu3_3, relu4_3 when `vgg_weights` names a file, otherwise the label-free FeatureNet trained on
    normal drives. Each level's channel-mean L1 map is resized bilinearly (align_corners=False) to
    the image size before summing.
    """

    name = "perceptual"

    def __init__(self, extractor: nn.Module, extractor_name: str, device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)  # where the net runs; the map comes back to the CPU
        # channels-last (NHWC) layout: the feature net's convolutions and pooling take less CPU, the map the
        # default layout's up to float rounding (docs/experiments.md); the (h, w, 3) images are NHWC already
        self.extractor = extractor.to(self.device, memory_format=torch.channels_last).eval().requires_grad_(False)
        self.extractor_name = extractor_name

    @classmethod
    def from_options(cls, options: MetricOptions) -> PerceptualDifference:
        torch.set_num_threads(options.threads)
        device = resolve_device(options.device)
        if options.vgg_weights is not None:
            from umad_common.models.vgg16 import load_vgg16_features

            return cls(load_vgg16_features(options.vgg_weights, device)[0], "vgg16", device)
        if options.features is None:
            raise DifferenceInputError(
                "perceptual: needs `vgg_weights` or `features` (a feature net file); got neither"
            )
        from umad_common.models.feature_net import load_feature_net

        return cls(load_feature_net(options.features, device)[0], "feature_net", device)

    @property
    def calibration_key(self) -> str:
        """VGG16 and the feature net have different scales, so each has its own calibration entry."""
        return "perceptual" if self.extractor_name == "feature_net" else f"perceptual/{self.extractor_name}"

    def compute(self, target, recon, preds, pred_valid):
        h, w = target.shape[:2]
        pair = torch.from_numpy(np.stack([target, recon])).permute(0, 3, 1, 2).to(self.device)  # (2, 3, h, w) NHWC
        with torch.inference_mode():
            total = torch.zeros(1, 1, h, w, device=self.device)
            for level in self.extractor(pair):
                dist = (level[0] - level[1]).abs().mean(dim=0, keepdim=True)[None]  # (1, 1, h_l, w_l)
                if dist.shape[-2:] != (h, w):
                    dist = F.interpolate(dist, size=(h, w), mode="bilinear", align_corners=False)
                total += dist
        return total[0, 0].cpu().numpy()

    def notes(self, pred_valid: np.ndarray) -> dict:
        return {"extractor": self.extractor_name}
