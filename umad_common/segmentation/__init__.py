"""Segmenters: the masks that mask-level refinement scores, one class per method.

    method = build_segmenter("felzenszwalb", {"scale": 100})
    masks = method(image, frame)        # (K, h, w) bool; image (h, w, 3) float32 in [0, 1]

Built-in methods (`SEGMENTERS`): `gt` (ground-truth instances + stuff regions, the upper-bound
ablation), `felzenszwalb`, `slic`, `kmeans` (image only, no labels), `learned` (clusters of a net trained
without labels on the domain's normal drives), `geometry` (lidar objects grown into image regions,
another method's segments elsewhere), `geometry_learned` (geometry with the learned segments) and
`sam` (segment-anything, in its own environment). A method not in `SEGMENTERS` loads by import path:
`build_segmenter("mypkg.mod:MySegmenter", {...})`, where `MySegmenter` subclasses `SegmenterMethod`.
`operators/segmenter.py` runs one per frame; `umad bench segmenters` measures them all.
"""

from __future__ import annotations

from typing import Any

from umad_common.dataflow import Context
from umad_common.datasets.sensor_rig import SensorRig
from umad_common.segmentation.base import (
    SegmenterInputError,
    SegmenterMethod,
    connected_regions,
    labels_to_masks,
    masks_to_labels,
)
from umad_common.segmentation.geometry import Geometry
from umad_common.segmentation.image import Felzenszwalb, KMeansSegments, Slic
from umad_common.segmentation.learned import GeometryLearned, Learned
from umad_common.segmentation.registry import SEGMENTERS, UnknownSegmenterError, register, segmenter_class
from umad_common.segmentation.sam import Sam
from umad_common.segmentation.truth import GroundTruth, gt_masks

register(GroundTruth, Felzenszwalb, Slic, KMeansSegments, Geometry, Learned, GeometryLearned, Sam)


def build_segmenter(
    name: str, options: dict[str, Any] | None = None, context: Context | None = None
) -> SegmenterMethod:
    """Construct a method by name or import path with its options (files load here, so bad ones fail early)."""
    return segmenter_class(name).from_options(options or {}, context)


__all__ = [
    "SEGMENTERS",
    "Felzenszwalb",
    "Geometry",
    "GeometryLearned",
    "GroundTruth",
    "KMeansSegments",
    "Learned",
    "Sam",
    "SegmenterInputError",
    "SegmenterMethod",
    "SensorRig",
    "Slic",
    "UnknownSegmenterError",
    "build_segmenter",
    "connected_regions",
    "gt_masks",
    "labels_to_masks",
    "masks_to_labels",
    "segmenter_class",
]
