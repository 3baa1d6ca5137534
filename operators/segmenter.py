"""Segmenter: the masks that mask-level refinement scores, from one of several methods.

- `gt`: ground-truth instance masks (the paper's upper-bound ablation), plus stuff regions;
- `felzenszwalb` / `slic`: graph-based and superpixel segmentation (scikit-image), no labels, no
  download;
- `kmeans`: per-pixel features (colour, position and gradient, or the label-free feature net's)
  clustered with k-means and split into connected components (the U2Seg idea without its detector);
- `sam`: segment-anything's automatic mask generator on a checkpoint file; the package needs
  torchvision and so torch 2.14.1, hence its own environment (`.ci/sam_env.sh`, graph field
  `python: .venv-sam/bin/python`).

Default `felzenszwalb`: on the built-in anomalous drives it isolates anomalies best of the
unsupervised built-ins at a few ms per frame (`umad bench segmenters`; the figures are defined in
`umad_common/benchmarks/segmentation_quality.py`).
Masks travel as one (K, h, w) bool array, so SAM's overlapping masks keep their overlaps.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from umad_common.operator import Context, Frame, Input, Operator, Output
from umad_common.segmentation import (
    FeatureNetFeatures,
    SamMasks,
    colour_features,
    felzenszwalb_masks,
    gt_masks,
    kmeans_masks,
    slic_masks,
)

SegmentFn = Callable[[np.ndarray, Frame], np.ndarray]


class SegmenterParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    method: Literal["gt", "felzenszwalb", "slic", "kmeans", "sam"] = Field(
        default="felzenszwalb",
        description="gt: ground-truth instances (+ stuff regions); felzenszwalb | slic: graph-based / "
        "superpixel segmentation; kmeans: feature clustering + connected components; sam: segment-anything",
    )
    gt_stuff: bool = Field(
        default=True,
        description="gt: also one mask per connected region of each semantic class among pixels without an "
        "instance (road, sidewalk, sky ...), so the masks tile the image",
    )
    gt_stuff_min_area: int = Field(default=16, ge=1, description="gt: stuff regions smaller than this get no mask")
    felzenszwalb_scale: float = Field(default=300.0, gt=0, description="felzenszwalb: larger -> fewer, larger segments")
    felzenszwalb_sigma: float = Field(default=0.3, ge=0, description="felzenszwalb: Gaussian pre-smoothing (px)")
    felzenszwalb_min_size: int = Field(default=15, ge=1, description="felzenszwalb: smallest segment (px)")
    slic_n_segments: int = Field(default=200, ge=1, description="slic: approximate number of superpixels")
    slic_compactness: float = Field(
        default=20.0, gt=0, description="slic: colour vs position balance; larger -> squarer superpixels"
    )
    slic_sigma: float = Field(default=1.0, ge=0, description="slic: Gaussian pre-smoothing (px)")
    kmeans_clusters: int = Field(default=32, ge=2, description="kmeans: number of feature clusters")
    kmeans_sigma: float = Field(default=0.5, ge=0, description="kmeans: Gaussian pre-smoothing of the image (px)")
    kmeans_position_weight: float = Field(
        default=0.25, ge=0, description="kmeans: weight of the (y, x) position features against Lab colour"
    )
    kmeans_gradient_weight: float = Field(
        default=0.0, ge=0, description="kmeans: weight of the local lightness-gradient feature"
    )
    kmeans_features: Literal["colour", "feature_net"] = Field(
        default="colour",
        description="kmeans: per-pixel features: colour (smoothed Lab + position + lightness gradient) or "
        "feature_net (the label-free feature net's first two levels + position; needs kmeans_feature_net)",
    )
    kmeans_feature_net: str = Field(
        default="",
        description="kmeans with feature_net: the trained feature net's safetensors file (its .json config "
        "beside it), relative to the graph's folder unless absolute",
    )
    kmeans_feature_weight: float = Field(
        default=1.0, gt=0, description="kmeans with feature_net: scale of the net's features against position"
    )
    kmeans_fit_stride: int = Field(
        default=3, ge=1, description="kmeans: fit centroids on every n-th pixel per direction, then assign all"
    )
    kmeans_min_area: int = Field(
        default=8, ge=1, description="kmeans: connected regions smaller than this get no mask (px)"
    )
    sam_checkpoint: str = Field(
        default="",
        description="sam: segment-anything state dict file (.pth or .safetensors) for sam_model, relative to "
        "the graph's folder unless absolute; never downloaded",
    )
    sam_model: Literal["vit_b", "vit_l", "vit_h"] = Field(default="vit_b", description="sam: model size")
    sam_points_per_side: int = Field(
        default=16, ge=1, description="sam: prompt grid is points_per_side^2 points (SAM's own default 32)"
    )
    sam_pred_iou_thresh: float = Field(
        default=0.88, ge=0, le=1, description="sam: drop masks whose predicted IoU is below"
    )
    sam_stability_score_thresh: float = Field(
        default=0.95, ge=0, le=1, description="sam: drop masks whose stability score is below"
    )
    sam_min_mask_region_area: int = Field(
        default=0, ge=0, description="sam: remove holes and islands smaller than this (px); 0 = off"
    )
    sam_device: str = Field(default="cpu", description="sam: torch device, e.g. cpu or cuda")


class Segmenter(Operator):
    """Per-frame segment masks of the world model's target image."""

    kind = "segmenter"
    inputs = (Input("frame"), Input("truth"))
    outputs = ("masks",)
    Params = SegmenterParams

    def __init__(self, params: BaseModel | dict | None = None, context: Context | None = None):
        super().__init__(params, context)
        self.segment = self.build(self.params)

    def update_params(self, params: BaseModel) -> None:
        """Rebuild the method first, so a bad new setting (e.g. a missing checkpoint) keeps the old one."""
        segment = self.build(params)
        self.params, self.segment = params, segment

    def build(self, p: SegmenterParams) -> SegmentFn:
        """The per-frame mask function for the parameters; loads SAM here, not at the first frame."""
        if p.method == "gt":
            return lambda image, frame: gt_masks(
                truth_array(frame, "instance"),
                image.shape[:2],
                semantic=frame.inputs["truth"].arrays.get("semantic"),
                stuff=p.gt_stuff,
                min_area=p.gt_stuff_min_area,
            )
        if p.method == "felzenszwalb":
            return lambda image, frame: felzenszwalb_masks(
                image, p.felzenszwalb_scale, p.felzenszwalb_sigma, p.felzenszwalb_min_size
            )
        if p.method == "slic":
            return lambda image, frame: slic_masks(image, p.slic_n_segments, p.slic_compactness, p.slic_sigma)
        if p.method == "kmeans" and p.kmeans_features == "feature_net":
            if not p.kmeans_feature_net:
                raise ValueError("segmenter kmeans_features 'feature_net' needs parameter kmeans_feature_net (a file)")
            features = FeatureNetFeatures(
                self.context.resolve(p.kmeans_feature_net), p.kmeans_feature_weight, p.kmeans_position_weight
            )
            return lambda image, frame: kmeans_masks(
                features(image), p.kmeans_clusters, p.kmeans_min_area, p.kmeans_fit_stride
            )
        if p.method == "kmeans":
            return lambda image, frame: kmeans_masks(
                colour_features(image, p.kmeans_sigma, p.kmeans_position_weight, p.kmeans_gradient_weight),
                p.kmeans_clusters,
                p.kmeans_min_area,
                p.kmeans_fit_stride,
            )
        if not p.sam_checkpoint:
            raise ValueError("segmenter method 'sam' needs parameter sam_checkpoint (a local checkpoint file)")
        sam = SamMasks(
            self.context.resolve(p.sam_checkpoint),
            p.sam_model,
            p.sam_points_per_side,
            p.sam_pred_iou_thresh,
            p.sam_stability_score_thresh,
            p.sam_min_mask_region_area,
            p.sam_device,
        )
        return lambda image, frame: sam(image)

    def process(self, frame: Frame) -> dict[str, Output]:
        target = frame.inputs["frame"].arrays.get("target")
        if target is None or target.ndim != 3 or target.shape[2] != 3:
            shape = None if target is None else target.shape
            raise ValueError(f"segmenter {frame.frame_id}: input 'frame' array 'target' is {shape}; expected (h, w, 3)")
        image = np.clip(np.asarray(target, dtype=np.float32), 0.0, 1.0)
        masks = self.segment(image, frame).astype(bool, copy=False)
        meta = {"method": self.params.method, "count": int(masks.shape[0])}
        return {"masks": Output({"masks": masks}, meta)}


def truth_array(frame: Frame, name: str) -> np.ndarray:
    """An array of the `truth` input, with an error naming what is missing."""
    truth = frame.inputs.get("truth")
    if truth is None or name not in truth.arrays:
        raise ValueError(f"segmenter {frame.frame_id}: method 'gt' needs input 'truth' with array {name!r}")
    return truth.arrays[name]
