"""Label-free segmenters that look at the image alone: Felzenszwalb graph segmentation, SLIC
superpixels and k-means feature clustering (the U2Seg idea without its detector). Each tiles the
image (every pixel in at most one mask); none needs a download."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage
from skimage.color import rgb2lab
from skimage.segmentation import felzenszwalb, slic
from threadpoolctl import threadpool_limits

from umad_common.dataflow import Context, Frame
from umad_common.models.device import DeviceName, device_field, resolve_device
from umad_common.segmentation.base import (
    TUNED,
    SegmenterMethod,
    connected_regions,
    labels_to_masks,
    sklearn_cluster,
)


class Felzenszwalb(SegmenterMethod):
    """Felzenszwalb-Huttenlocher graph segmentation (scikit-image)."""

    name = "felzenszwalb"
    tuning_grid = {"scale": [50.0, 100.0, 200.0, 300.0], "sigma": [0.3, 0.8]}

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

        scale: float = Field(300.0, gt=0, description=f"larger -> fewer, larger segments; {TUNED}")
        sigma: float = Field(0.3, ge=0, description=f"Gaussian pre-smoothing (px); {TUNED}")
        min_size: int = Field(15, ge=1, description="smallest segment (px)")

    def __call__(self, image: np.ndarray, frame: Frame) -> np.ndarray:
        p = self.params
        labels = felzenszwalb(image, scale=p.scale, sigma=p.sigma, min_size=p.min_size, channel_axis=-1)
        return labels_to_masks(labels)


class Slic(SegmenterMethod):
    """SLIC superpixels (k-means in Lab + position, scikit-image)."""

    name = "slic"
    tuning_grid = {"n_segments": [100, 200, 300], "compactness": [10.0, 20.0]}

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

        n_segments: int = Field(100, ge=1, description=f"approximate number of superpixels; {TUNED}")
        compactness: float = Field(20.0, gt=0, description=f"colour vs position balance; larger -> squarer; {TUNED}")
        sigma: float = Field(1.0, ge=0, description="Gaussian pre-smoothing (px)")

    def __call__(self, image: np.ndarray, frame: Frame) -> np.ndarray:
        p = self.params
        labels = slic(
            image, n_segments=p.n_segments, compactness=p.compactness, sigma=p.sigma, start_label=0, channel_axis=-1
        )
        return labels_to_masks(labels)


def colour_features(image: np.ndarray, sigma: float, position_weight: float, gradient_weight: float) -> np.ndarray:
    """(h, w, 6) per-pixel features: smoothed Lab colour scaled to ~[0, 1], (y, x) position and the
    local gradient magnitude of lightness, each group scaled by its weight."""
    smooth = ndimage.gaussian_filter(image, sigma=(sigma, sigma, 0)) if sigma > 0 else image
    lab = rgb2lab(smooth) / np.array([100.0, 128.0, 128.0])
    h, w = image.shape[:2]
    ys, xs = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    lightness = lab[..., 0]
    gradient = np.hypot(ndimage.sobel(lightness, axis=0), ndimage.sobel(lightness, axis=1))
    gradient = ndimage.gaussian_filter(gradient, sigma=max(sigma, 1.0))
    return np.concatenate(
        [lab, position_weight * np.stack([ys, xs], axis=-1), gradient_weight * gradient[..., None]], axis=-1
    ).astype(np.float32)


class FeatureNetFeatures:
    """(h, w, C) per-pixel features from the label-free feature net (`umad train features`): its
    first two levels upsampled to the image, each channel standardised over the frame, the whole
    group scaled to total variance `weight**2`; then the (y, x) position like `colour_features`."""

    LEVELS = 2  # full and half resolution: the finer levels carry object boundaries

    def __init__(self, weights: Path, weight: float, position_weight: float, device: str = "cpu"):
        import torch

        from umad_common.models.feature_net import load_feature_net

        self.torch = torch
        self.device = resolve_device(device)
        self.net, _ = load_feature_net(weights, self.device)
        self.weight = weight
        self.position_weight = position_weight

    def __call__(self, image: np.ndarray) -> np.ndarray:
        torch = self.torch
        h, w = image.shape[:2]
        with torch.inference_mode():
            batch = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None]  # (1, 3, h, w)
            levels = self.net(batch.to(self.device))[: self.LEVELS]
            upsampled = [torch.nn.functional.interpolate(x, size=(h, w), mode="bilinear") for x in levels]
            features = torch.cat(upsampled, dim=1)[0].permute(1, 2, 0).cpu().numpy()  # (h, w, C)
        flat = features.reshape(-1, features.shape[-1]).astype(np.float64)
        flat = (flat - flat.mean(axis=0)) / (flat.std(axis=0) + 1e-6) / np.sqrt(flat.shape[1])
        ys, xs = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
        position = self.position_weight * np.stack([ys, xs], axis=-1)
        return np.concatenate([self.weight * flat.reshape(h, w, -1), position], axis=-1).astype(np.float32)


def kmeans_masks(features: np.ndarray, clusters: int, min_area: int, fit_stride: int = 1, seed: int = 0) -> np.ndarray:
    """Feature clustering + connected components: k-means on per-pixel features, then each
    4-connected region of one cluster becomes a mask.

    Args:
        features: (h, w, C) per-pixel features.
        clusters: k of k-means.
        min_area: smaller regions get no mask (their pixels stay uncovered).
        fit_stride: fit the centroids on every n-th pixel in each direction, then assign every pixel
            to its nearest centroid (n^2 times less fitting work).
        seed: k-means initialisation seed (fixed: the same frame gives the same masks).
    """
    h, w, channels = features.shape
    sample = features[::fit_stride, ::fit_stride].reshape(-1, channels)
    with threadpool_limits(1):  # ~25k points: thread start-up costs more than it saves
        kmeans = sklearn_cluster().KMeans(
            n_clusters=min(clusters, len(sample)), n_init=1, max_iter=50, random_state=seed
        )
        kmeans.fit(sample)
        assignment = kmeans.predict(features.reshape(-1, channels))
    regions = connected_regions(assignment.reshape(h, w))
    return labels_to_masks(regions, min_area=min_area)


class KMeansSegments(SegmenterMethod):
    """k-means on per-pixel features (colour, or the label-free feature net's) + connected components."""

    name = "kmeans"
    tuning_grid = {"clusters": [16, 32, 48], "position_weight": [0.25, 0.5]}

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

        clusters: int = Field(16, ge=2, description=f"number of feature clusters; {TUNED}")
        sigma: float = Field(0.5, ge=0, description="Gaussian pre-smoothing of the image (px)")
        position_weight: float = Field(
            0.5, ge=0, description=f"weight of the (y, x) position against Lab colour; {TUNED}"
        )
        gradient_weight: float = Field(0.0, ge=0, description="weight of the local lightness-gradient feature")
        features: Literal["colour", "feature_net"] = Field(
            "colour",
            description="colour (smoothed Lab + position + lightness gradient) or feature_net (the label-free "
            "feature net's first two levels + position; needs `feature_net`)",
        )
        feature_net: str = Field(
            "",
            description="features: feature_net: the trained net's safetensors file (its .json config beside it), "
            "relative to the graph's folder unless absolute",
        )
        feature_weight: float = Field(
            1.0, gt=0, description="feature_net: scale of the net's features against position"
        )
        fit_stride: int = Field(3, ge=1, description="fit centroids on every n-th pixel per direction, then assign all")
        min_area: int = Field(8, ge=1, description="connected regions smaller than this get no mask (px)")
        device: DeviceName = device_field()

    def __init__(self, params: BaseModel, context: Context):
        super().__init__(params, context)
        p = self.params
        sklearn_cluster()  # at start-up, not on the first frame
        self.net_features = None
        if p.features == "feature_net":
            if not p.feature_net:
                raise ValueError(
                    "segmenter method 'kmeans' with features 'feature_net' needs option feature_net (a file)"
                )
            self.net_features = FeatureNetFeatures(
                context.resolve(p.feature_net), p.feature_weight, p.position_weight, p.device
            )

    def __call__(self, image: np.ndarray, frame: Frame) -> np.ndarray:
        p = self.params
        if self.net_features is not None:
            features = self.net_features(image)
        else:
            features = colour_features(image, p.sigma, p.position_weight, p.gradient_weight)
        return kmeans_masks(features, p.clusters, p.min_area, p.fit_stride)
