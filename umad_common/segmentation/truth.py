"""Ground-truth masks (the paper's upper-bound ablation): instances plus stuff regions."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from umad_common.dataflow import Frame, input_array
from umad_common.refine import resize_nearest
from umad_common.segmentation.base import SegmenterMethod, connected_regions, labels_to_masks


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


class GroundTruth(SegmenterMethod):
    """Ground-truth instance masks from the `truth` input, plus stuff regions."""

    name = "gt"
    needs = ("truth",)
    tuning_grid = {"stuff": [True, False]}

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

        stuff: bool = Field(
            True,
            description="also one mask per connected region of each semantic class among pixels without an "
            "instance (road, sidewalk, sky ...), so the masks tile the image",
        )
        stuff_min_area: int = Field(16, ge=1, description="stuff regions smaller than this get no mask (px)")

    def __call__(self, image: np.ndarray, frame: Frame) -> np.ndarray:
        instance = input_array(frame, "truth", "instance", f"segmenter method {self.name!r}")
        semantic = frame.inputs["truth"].arrays.get("semantic")
        return gt_masks(instance, image.shape[:2], semantic, self.params.stuff, self.params.stuff_min_area)
