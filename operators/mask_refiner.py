"""Mask refiner: turns the fused pixel map into object-level scores with a segmenter's masks.

`mean` (the paper's default) writes each mask's mean fused score to its pixels, so a whole object
lights up instead of speckles and high-frequency normal structure is averaged down. The arithmetic,
the overlap rule (the highest score wins) and the uncovered-pixel rule live in
`umad_common.refine.refine`, shared with the offline sweep.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from umad_common.dataflow import Frame, Input, Operator, Output, input_array
from umad_common.refine import refine, resize_nearest


class MaskRefinerParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    mode: Literal["mean", "max", "single", "single_keep_raw", "none"] = Field(
        default="mean",
        description="mean | max: each mask's mean | max fused score written to its pixels (the highest score "
        "wins where masks overlap); single: only the mask with the highest mean keeps its score, every other "
        "pixel gets the frame's lowest (the paper's); single_keep_raw: the same survivor, other pixels follow "
        "`uncovered`; none: the fused map",
    )
    uncovered: Literal["keep", "zero"] = Field(
        default="keep",
        description="pixels covered by no surviving mask (all modes but single): keep their fused score (an object the segmenter "
        "missed still shows its raw evidence) or set them to zero",
    )


class MaskRefiner(Operator):
    """Per-frame mask-level refinement of the fused map."""

    kind = "mask_refiner"
    inputs = (Input("fused"), Input("masks"))
    outputs = ("refined",)
    Params = MaskRefinerParams

    def process(self, frame: Frame) -> dict[str, Output]:
        fused = input_array(frame, "fused", "map", self.kind)
        masks = input_array(frame, "masks", "masks", self.kind)
        if fused.ndim != 2 or masks.ndim != 3:
            raise ValueError(
                f"mask_refiner {frame.frame_id}: got fused {fused.shape} and masks {masks.shape}; "
                "expected (h, w) and (K, h', w')"
            )
        masks = resize_nearest(masks.astype(bool, copy=False), fused.shape)
        refined = refine(fused, masks, mode=self.params.mode, uncovered=self.params.uncovered)
        meta = {
            "mode": self.params.mode,
            "uncovered": self.params.uncovered,
            "masks": int(masks.shape[0]),
            "partial": bool(frame.inputs["fused"].meta.get("partial", False)),  # the fused map lacked a late map
        }
        return {"refined": Output({"map": refined}, meta)}
