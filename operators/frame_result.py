"""Frame result: what a consumer on the vehicle acts on, per frame, in a few hundred bytes.

From the refined map and the masks that refined it: the frame's anomaly score (the refined map's
maximum) and the `top_k` masks by score, each as a box (x0, y0, x1, y1: pixel edges, the box
covers columns x0 <= x < x1 and rows y0 <= y < y1) and its score (the refined map's mean over the
mask). Boxes are in the camera's pixels when `camera` is wired (the maps are at the world model's
size), else in the map's. `partial` says the fused map lacked a difference map that missed the
live deadline (the mask refiner passes it on).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from umad_common.dataflow import Frame, Input, Operator, Output, input_array
from umad_common.refine import mask_scores
from umad_operators.mask_refiner import map_and_masks


class FrameResultParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    top_k: int = Field(5, ge=0, description="how many masks to report, highest score first")
    min_score: float = Field(
        0.0, ge=0.0, description="masks scoring below this are not reported (0: the top_k whatever their score)"
    )


def mask_boxes(masks: np.ndarray) -> np.ndarray:
    """(K, 4) int64 boxes (x0, y0, x1, y1, end exclusive) of non-empty (K, h, w) bool masks."""
    rows = masks.any(axis=2)  # (K, h)
    cols = masks.any(axis=1)  # (K, w)
    y0 = rows.argmax(axis=1)
    y1 = rows.shape[1] - rows[:, ::-1].argmax(axis=1)
    x0 = cols.argmax(axis=1)
    x1 = cols.shape[1] - cols[:, ::-1].argmax(axis=1)
    return np.stack([x0, y0, x1, y1], axis=1)


def frame_result(
    refined: np.ndarray,
    masks: np.ndarray,
    top_k: int,
    min_score: float = 0.0,
    image_size: tuple[int, int] | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """The frame's score, the top masks' boxes and their scores.

    Args:
        refined: (h, w) refined anomaly map.
        masks: (K, h, w) bool masks at the map's size.
        top_k: at most this many boxes, highest score first (ties: lowest mask index).
        min_score: masks scoring below it are left out.
        image_size: (height, width) the boxes are scaled to; None: the map's pixels.

    Returns:
        score (max of `refined`, 0 for an empty map), boxes (k, 4) float32 (x0, y0, x1, y1),
        scores (k,) float32.
    """
    h, w = refined.shape
    score = float(refined.max()) if refined.size else 0.0
    scores = mask_scores(refined, masks, "mean") if masks.shape[0] else np.zeros(0)
    order = np.argsort(-scores, kind="stable")[:top_k]
    order = order[np.isfinite(scores[order]) & (scores[order] >= min_score)]
    boxes = mask_boxes(masks[order]).astype(np.float64)
    if image_size is not None:
        boxes *= np.array([image_size[1] / w, image_size[0] / h] * 2)
    return score, np.round(boxes).astype(np.float32), scores[order].astype(np.float32)


class FrameResult(Operator):
    """Per frame: the anomaly score and the top masks' boxes and scores."""

    kind = "frame_result"
    inputs = (Input("refined"), Input("masks"), Input("camera", optional=True))
    outputs = ("result",)
    Params = FrameResultParams

    def process(self, frame: Frame) -> dict[str, Output]:
        refined, masks = map_and_masks(frame, "refined", self.kind)
        image_size = None
        if "camera" in frame.inputs:
            image_size = tuple(input_array(frame, "camera", "rgb", self.kind).shape[:2])
        score, boxes, box_scores = frame_result(refined, masks, self.params.top_k, self.params.min_score, image_size)
        meta = {
            "score": score,
            "boxes": len(boxes),
            "image_size": list(image_size or refined.shape),
            "partial": bool(frame.inputs["refined"].meta.get("partial", False)),
        }
        arrays = {"score": np.array([score], np.float32), "boxes": boxes, "box_scores": box_scores}
        return {"result": Output(arrays, meta)}
