"""Segmenter: the masks that mask-level refinement scores, from one registered method.

The methods live in `umad_common.segmentation` (one class each, with its own options); this
operator runs one per frame on the world model's target image:

    segment_unsup:
      kind: segmenter
      inputs: {frame: world_model/frame, lidar: replayer/lidar}   # truth: replayer/truth for gt
      params: {method: geometry, options: {rest: slic}}

or on the camera image itself, resized to `image_size` as the world model resizes it (the same
pixels, so the same masks), without waiting for the world model: the live graph does, so the
segmenter works while the world model does and the refined map comes one stage sooner:

      inputs: {camera: replayer/camera, lidar: replayer/lidar}
      params: {method: geometry, image_size: [192, 128]}

`truth` and `lidar` are wired only where the method reads them; `umad graph check` names a method
whose input is missing. Masks travel as one (K, h, w) bool array, so SAM's overlaps survive.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from umad_common.dataflow import Context, Frame, Input, Operator, Output
from umad_common.segmentation import SEGMENTERS, SegmenterMethod, UnknownSegmenterError, segmenter_class


class SegmenterParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    method: str = Field(
        "slic",
        description=f"one of {sorted(SEGMENTERS)}, or `package.module:Class` of a SegmenterMethod; slic: the "
        "best method that needs the image alone (geometry, which needs lidar, was better), chosen on validation "
        "seed 2 (best refined AP) by `umad bench segmenters`",
    )
    options: dict[str, Any] = Field(
        default_factory=dict, description="the method's own parameters (its `Params`; unset ones take its defaults)"
    )
    image_size: tuple[int, int] = Field(
        (192, 128),
        description="width, height the `camera` input is resized to (area averaging, as the world model resizes "
        "its input): the world model's image size, so masks match its maps; unused with the `frame` input",
    )

    @model_validator(mode="after")
    def _options_fit_the_method(self) -> SegmenterParams:
        try:
            segmenter_class(self.method).Params.model_validate(self.options)
        except UnknownSegmenterError as exc:
            raise ValueError(str(exc)) from None
        except ValidationError as exc:
            problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'options'}: {e['msg']}" for e in exc.errors())
            raise ValueError(f"method {self.method!r} options: {problems}") from None
        return self


class Segmenter(Operator):
    """Per-frame segment masks of the world model's target image (or of the camera image, resized)."""

    kind = "segmenter"
    inputs = (
        Input("frame", optional=True),
        Input("camera", optional=True),
        Input("truth", optional=True),
        Input("lidar", optional=True),
    )
    outputs = ("masks",)
    Params = SegmenterParams

    def __init__(self, params: BaseModel | dict | None = None, context: Context | None = None):
        super().__init__(params, context)
        self.method = self.build(self.params)

    @classmethod
    def wiring_problems(cls, params: BaseModel, wired: set[str]) -> list[str]:
        method = segmenter_class(params.method)
        needed = method.required_inputs(method.Params.model_validate(params.options))
        problems = [
            f"method {params.method!r} needs input {port!r} (e.g. replayer/{port}), which is not wired"
            for port in sorted(needed - wired)
        ]
        images = sorted({"frame", "camera"} & wired)
        if len(images) != 1:
            problems.append(
                f"wire exactly one image input, frame (world_model/frame) or camera (replayer/camera); got {images}"
            )
        return problems

    def update_params(self, params: BaseModel) -> None:
        """Build the new method first, so a bad new setting (e.g. a missing checkpoint) keeps the old one."""
        method = self.build(params)
        self.params, self.method = params, method

    def build(self, params: SegmenterParams) -> SegmenterMethod:
        """The method for the parameters; weight files load here, not at the first frame."""
        return segmenter_class(params.method).from_options(params.options, self.context)

    def process(self, frame: Frame) -> dict[str, Output]:
        port, name = ("frame", "target") if "frame" in frame.inputs else ("camera", "rgb")
        image = frame.inputs[port].arrays.get(name) if port in frame.inputs else None
        if image is None or image.ndim != 3 or image.shape[2] != 3:
            shape = None if image is None else image.shape
            raise ValueError(
                f"segmenter {frame.frame_id}: input {port!r} array {name!r} is {shape}; expected (h, w, 3)"
            )
        if port == "camera":  # as the world model makes its target (`resize_rgb`), so the same pixels
            resized = cv2.resize(np.asarray(image, np.uint8), self.params.image_size, interpolation=cv2.INTER_AREA)
            image = resized.astype(np.float32) / 255.0
        else:
            image = np.clip(np.asarray(image, dtype=np.float32), 0.0, 1.0)
        masks = self.method(image, frame).astype(bool, copy=False)
        meta = {"method": self.params.method, "count": int(masks.shape[0])}
        return {"masks": Output({"masks": masks}, meta)}
