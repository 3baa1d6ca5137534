"""Mask refiner: turns the fused pixel map into object-level scores with a segmenter's masks.

`mean` (the paper's default) writes each mask's mean fused score to its pixels, so a whole object
lights up instead of speckles and high-frequency normal structure is averaged down. `mean_pixel`
(ours, what the default graphs run on label-free masks) keeps a share of each pixel's own score
beside its mask's mean, so a small object inside a large segment is not averaged away. The
arithmetic, the overlap rule (the highest score wins) and the uncovered-pixel rule live in
`umad_common.refine.refine`, shared with the offline sweep.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from umad_common.dataflow import Frame, Input, Operator, Output, input_array
from umad_common.refine import PIXEL_SHARE, refine, resize_nearest


class MaskRefinerParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    mode: Literal["mean", "mean_pixel", "max", "single", "single_keep_raw", "none"] = Field(
        default="mean",
        description="mean | max: each mask's mean | max fused score written to its pixels (the highest score "
        "wins where masks overlap); mean_pixel (ours): mean, then each covered pixel keeps `pixel_share` of its "
        "own fused score; single: only the mask with the highest mean keeps its score, every other "
        "pixel gets the frame's lowest (the paper's); single_keep_raw: the same survivor, other pixels follow "
        "`uncovered`; none: the fused map",
    )
    pixel_share: float = Field(
        default=PIXEL_SHARE,
        ge=0.0,
        le=1.0,
        description="mean_pixel only: the share of a covered pixel's own fused score beside its mask's mean "
        "(0: the paper's mean; the default was chosen on validation seeds 2 and 31)",
    )
    uncovered: Literal["keep", "zero"] = Field(
        default="keep",
        description="pixels covered by no surviving mask (all modes but single): keep their fused score (an object the segmenter "
        "missed still shows its raw evidence) or set them to zero",
    )


def map_and_masks(frame: Frame, map_port: str, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """A frame's score map (port `map_port`, array `map`, (h, w)) and its masks (port `masks`,
    (K, h', w')) resized to the map's size as bool; a ValueError naming both shapes otherwise."""
    score_map = input_array(frame, map_port, "map", kind)
    masks = input_array(frame, "masks", "masks", kind)
    if score_map.ndim != 2 or masks.ndim != 3:
        raise ValueError(
            f"{kind} {frame.frame_id}: got {map_port} {score_map.shape} and masks {masks.shape}; "
            "expected (h, w) and (K, h', w')"
        )
    return score_map, resize_nearest(masks.astype(bool, copy=False), score_map.shape)


class MaskRefiner(Operator):
    """Per-frame mask-level refinement of the fused map."""

    kind = "mask_refiner"
    inputs = (Input("fused"), Input("masks"))
    outputs = ("refined",)
    Params = MaskRefinerParams

    def process(self, frame: Frame) -> dict[str, Output]:
        fused, masks = map_and_masks(frame, "fused", self.kind)
        refined = refine(
            fused, masks, mode=self.params.mode, uncovered=self.params.uncovered, pixel_share=self.params.pixel_share
        )
        meta = {
            "mode": self.params.mode,
            "uncovered": self.params.uncovered,
            "masks": int(masks.shape[0]),
            **({"pixel_share": self.params.pixel_share} if self.params.mode == "mean_pixel" else {}),
            "partial": bool(frame.inputs["fused"].meta.get("partial", False)),  # the fused map lacked a late map
        }
        return {"refined": Output({"map": refined}, meta)}
