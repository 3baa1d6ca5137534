"""The `learned` segmenter: segments from the label-free segment net trained on the domain's normal
drives (`umad train segmenter`, `umad_common.models.segment_net`), and `geometry_learned`, the
lidar's objects with learned segments elsewhere.

Per frame: each pixel's cluster (its nearest prototype), 4-connected regions of one cluster, regions
smaller than `min_area` absorbed by their nearest large region; the masks tile the frame.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from umad_common.dataflow import Context, Frame
from umad_common.models.device import DeviceName, device_field, resolve_device
from umad_common.segmentation.base import TUNED, SegmenterMethod, connected_regions, labels_to_masks
from umad_common.segmentation.geometry import Geometry

SHIPPED = "umad_common/assets/segment_net.safetensors"  # trained on the built-in world's normal drives, seed 0


def merge_small_regions(regions: np.ndarray, min_area: int) -> np.ndarray:
    """(h, w) region ids 0..n-1 -> ids where every region smaller than `min_area` px has gone to the
    large region nearest to each of its pixels (all stay when none is large), renumbered to
    4-connected regions."""
    sizes = np.bincount(regions.reshape(-1))
    small = sizes[regions] < min_area
    if small.all() or not small.any():
        return regions
    _, (rows, cols) = ndimage.distance_transform_edt(small, return_indices=True)
    return connected_regions(regions[rows, cols])


class Learned(SegmenterMethod):
    """Cluster ids of the label-free segment net, split into connected regions."""

    name = "learned"
    tuning_grid = {"min_area": [16, 48, 128, 256]}

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

        weights: str = Field(
            SHIPPED,
            description="the segment net's safetensors file (its .json beside it), relative to the graph's folder "
            "unless absolute; the default is shipped (`umad train segmenter` on seed 0's normal drives)",
        )
        min_area: int = Field(
            48, ge=1, description=f"regions smaller than this (px) join their nearest neighbour; {TUNED}"
        )
        device: DeviceName = device_field()

    def __init__(self, params: BaseModel, context: Context):
        super().__init__(params, context)
        import torch

        from umad_common.models.segment_net import load_segment_net

        self.torch = torch
        self.device = resolve_device(self.params.device)
        self.net, _ = load_segment_net(context.resolve(self.params.weights), self.device)

    def __call__(self, image: np.ndarray, frame: Frame) -> np.ndarray:
        torch = self.torch
        batch = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None]  # (1, 3, h, w)
        clusters = self.net.cluster_ids(batch.to(self.device))[0].cpu().numpy()  # (h, w)
        regions = merge_small_regions(connected_regions(clusters), self.params.min_area)
        return labels_to_masks(regions)


class GeometryLearned(Geometry):
    """`geometry` with the `learned` segments as its rest: lidar objects where the lidar sees one,
    learned segments elsewhere."""

    name = "geometry_learned"
    tuning_grid = {"rest_options": [{"min_area": area} for area in (256, 512, 1024, 2048)]}

    class Params(Geometry.Params):
        rest: str = Field(
            "learned", description="the method whose segments cover the rest of the frame and grow the objects"
        )
        rest_options: dict[str, Any] = Field(
            default_factory=lambda: {"min_area": 1024},
            description="the learned segments' options; min_area far larger than `learned`'s own: the lidar finds "
            f"the objects, the rest only needs large normal regions to average over; {TUNED}",
        )
