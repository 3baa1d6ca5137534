"""Segment masks for mask-level refinement: ground truth, graph-based, feature clustering and SAM.

Every function returns (K, h, w) bool masks (K may be 0) for a (h, w, 3) float32 image in [0, 1].
Graph-based segmenters and k-means tile the image (each pixel in at most one mask); SAM's masks
overlap. `operators/segmenter.py` picks one by its `method` parameter; `umad bench segmenters`
(`umad_common/benchmarks/segmentation_quality.py`) measures the same functions offline.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage
from skimage.color import rgb2lab
from skimage.measure import label as label_regions
from skimage.segmentation import felzenszwalb, slic
from sklearn.cluster import KMeans
from threadpoolctl import threadpool_limits

from umad_common.refine import resize_nearest


def labels_to_masks(labels: np.ndarray, min_area: int = 1, ignore: int | None = None) -> np.ndarray:
    """One bool mask per distinct label with at least `min_area` pixels, largest first.

    Args:
        labels: (h, w) integer label map.
        min_area: smaller regions get no mask (their pixels stay uncovered).
        ignore: a label value that gets no mask (e.g. 0 = "no instance").
    """
    ids, counts = np.unique(labels, return_counts=True)
    keep = counts >= min_area
    if ignore is not None:
        keep &= ids != ignore
    ids, counts = ids[keep], counts[keep]
    ids = ids[np.argsort(-counts, kind="stable")]
    return labels[None, :, :] == ids[:, None, None]


def connected_regions(labels: np.ndarray) -> np.ndarray:
    """Relabel so that each 4-connected region of equal label gets its own id (0..n-1); pixels
    labelled -1 stay -1."""
    return label_regions(labels, background=-1, connectivity=1) - 1


def gt_masks(
    instance: np.ndarray,
    shape: tuple[int, int],
    semantic: np.ndarray | None = None,
    stuff: bool = True,
    min_area: int = 1,
) -> np.ndarray:
    """Ground-truth masks: one per instance id > 0, plus (if `stuff`) one per connected region of
    each semantic class among the pixels without an instance (road, sidewalk, sky, buildings ...),
    which makes the masks tile the image like a panoptic segmentation.

    Args:
        instance: (H, W) int instance ids at full size (0 = no instance); resized nearest to `shape`.
        shape: mask size (h, w).
        semantic: (H, W) semantic class ids at full size, needed for `stuff`.
        stuff: add the stuff regions (ignored when `semantic` is None).
        min_area: smaller stuff regions get no mask; instances always keep theirs.
    """
    instance = resize_nearest(np.asarray(instance), shape)
    things = labels_to_masks(instance, min_area=1, ignore=0)
    if not stuff or semantic is None:
        return things
    semantic = resize_nearest(np.asarray(semantic), shape).astype(np.int64)
    no_instance = instance == 0
    regions = connected_regions(np.where(no_instance, semantic, -1))  # instance pixels -> -1
    stuff_masks = labels_to_masks(regions, min_area=min_area, ignore=-1)
    return np.concatenate([things, stuff_masks], axis=0)


def felzenszwalb_masks(image: np.ndarray, scale: float, sigma: float, min_size: int) -> np.ndarray:
    """Felzenszwalb-Huttenlocher graph segmentation (scikit-image); masks tile the image."""
    labels = felzenszwalb(image, scale=scale, sigma=sigma, min_size=min_size, channel_axis=-1)
    return labels_to_masks(labels)


def slic_masks(image: np.ndarray, n_segments: int, compactness: float, sigma: float) -> np.ndarray:
    """SLIC superpixels (k-means in Lab + position, scikit-image); masks tile the image."""
    labels = slic(image, n_segments=n_segments, compactness=compactness, sigma=sigma, start_label=0, channel_axis=-1)
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

    def __init__(self, weights: Path, weight: float, position_weight: float):
        import torch

        from umad_common.models.feature_net import load_feature_net

        self.torch = torch
        self.net = load_feature_net(weights)
        self.weight = weight
        self.position_weight = position_weight

    def __call__(self, image: np.ndarray) -> np.ndarray:
        torch = self.torch
        h, w = image.shape[:2]
        with torch.inference_mode():
            batch = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None]  # (1, 3, h, w)
            levels = self.net(batch)[: self.LEVELS]
            upsampled = [torch.nn.functional.interpolate(x, size=(h, w), mode="bilinear") for x in levels]
            features = torch.cat(upsampled, dim=1)[0].permute(1, 2, 0).numpy()  # (h, w, C)
        flat = features.reshape(-1, features.shape[-1]).astype(np.float64)
        flat = (flat - flat.mean(axis=0)) / (flat.std(axis=0) + 1e-6) / np.sqrt(flat.shape[1])
        ys, xs = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
        position = self.position_weight * np.stack([ys, xs], axis=-1)
        return np.concatenate([self.weight * flat.reshape(h, w, -1), position], axis=-1).astype(np.float32)


def kmeans_masks(features: np.ndarray, clusters: int, min_area: int, fit_stride: int = 1, seed: int = 0) -> np.ndarray:
    """Feature clustering + connected components (the U2Seg idea without its detector): k-means on
    per-pixel features, then each 4-connected region of one cluster becomes a mask.

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
        kmeans = KMeans(n_clusters=min(clusters, len(sample)), n_init=1, max_iter=50, random_state=seed)
        kmeans.fit(sample)
        assignment = kmeans.predict(features.reshape(-1, channels))
    regions = connected_regions(assignment.reshape(h, w))
    return labels_to_masks(regions, min_area=min_area)


class SamMasks:
    """segment-anything's automatic mask generator on a checkpoint file (no download).

    Construction loads everything (fails at start, not at the first frame): the package, the
    checkpoint (`torch.load(weights_only=True)` or safetensors) and the model.
    """

    def __init__(
        self,
        checkpoint: Path,
        model_type: str,
        points_per_side: int,
        pred_iou_thresh: float,
        stability_score_thresh: float,
        min_mask_region_area: int,
        device: str = "cpu",
    ):
        if not checkpoint.is_file():
            raise FileNotFoundError(
                f"segmenter method 'sam': checkpoint file {checkpoint} does not exist; expected a segment-anything "
                f"{model_type} state dict (.pth or .safetensors) named by parameter sam_checkpoint"
            )
        try:
            import torch
            from segment_anything import SamAutomaticMaskGenerator, sam_model_registry
        except ImportError as exc:
            raise ImportError(
                f"segmenter method 'sam' needs the segment-anything package (and torchvision) but importing it "
                f"failed ({exc}); build its environment with `.ci/sam_env.sh` and run this operator there with "
                "the graph field `python: .venv-sam/bin/python`"
            ) from exc
        if model_type not in sam_model_registry:
            raise ValueError(
                f"segmenter: sam_model {model_type!r} unknown; expected one of {sorted(sam_model_registry)}"
            )
        if checkpoint.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(checkpoint), device=device)
        else:
            state = torch.load(checkpoint, map_location=device, weights_only=True)
        model = sam_model_registry[model_type](checkpoint=None)
        try:
            model.load_state_dict(state)
        except RuntimeError as exc:
            raise ValueError(f"segmenter: {checkpoint} is not a {model_type} SAM checkpoint: {exc}") from None
        model.to(device).eval()
        self.torch = torch
        self.generator = SamAutomaticMaskGenerator(
            model,
            points_per_side=points_per_side,
            pred_iou_thresh=pred_iou_thresh,
            stability_score_thresh=stability_score_thresh,
            min_mask_region_area=min_mask_region_area,
            output_mode="binary_mask",
        )

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(K, h, w) bool masks, largest first; they may overlap."""
        rgb = np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)
        with self.torch.inference_mode():
            records = self.generator.generate(rgb)
        if not records:
            return np.zeros((0, *image.shape[:2]), dtype=bool)
        records.sort(key=lambda r: -int(r["area"]))
        return np.stack([np.asarray(r["segmentation"], dtype=bool) for r in records])
