"""Foxglove views of a run: images of the bus messages as `foxglove.CompressedImage` JSON messages.

The recorder adds them on `viz/<op>/<output>` channels beside the exact payloads, so a log opens in
Foxglove with the camera, the reconstruction, every difference map and the anomaly scores visible.
Replay and sweeps ignore these channels (they are JSON, not msgpack).
"""

from __future__ import annotations

import base64

import cv2
import numpy as np

from umad_common.dataflow.messages import Message

COMPRESSED_IMAGE_SCHEMA = {
    "title": "foxglove.CompressedImage",
    "description": "A compressed image",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
        },
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}


def _colour_map(score: np.ndarray) -> np.ndarray:
    """A [0, 1] score map as a BGR heat map."""
    lo, hi = float(np.min(score)), float(np.max(score))
    scaled = np.zeros_like(score, np.uint8) if hi <= lo else ((score - lo) / (hi - lo) * 255).astype(np.uint8)
    return cv2.applyColorMap(scaled, cv2.COLORMAP_INFERNO)


def _boxes_picture(msg: Message) -> np.ndarray:
    """A frame result's boxes on a dark canvas of the image's size: each outlined in its score's
    colour with the score beside it, the frame's score in the top-left corner."""
    boxes = msg.arrays["boxes"]
    extent = (int(boxes[:, 3].max()), int(boxes[:, 2].max())) if len(boxes) else (1, 1)
    height, width = (int(n) for n in msg.meta.get("image_size", extent))
    picture = np.zeros((height, width, 3), np.uint8)
    colours = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_INFERNO)[:, 0]
    for (x0, y0, x1, y1), score in zip(boxes, msg.arrays["box_scores"], strict=True):
        colour = tuple(int(c) for c in colours[int(np.clip(score, 0, 1) * 255)])
        cv2.rectangle(picture, (int(x0), int(y0)), (int(x1) - 1, int(y1) - 1), colour, 2)
        cv2.putText(picture, f"{score:.2f}", (int(x0), max(int(y0) - 3, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour)
    frame_score = float(msg.arrays["score"][0])
    partial = " partial" if msg.meta.get("partial") else ""
    cv2.putText(picture, f"score {frame_score:.3f}{partial}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255))
    return picture


def views(output: str, msg: Message) -> dict[str, np.ndarray]:
    """BGR uint8 pictures worth showing for one message, by sub-name."""
    arrays = msg.arrays
    if "boxes" in arrays and "box_scores" in arrays and "score" in arrays:
        return {"": _boxes_picture(msg)}
    if "rgb" in arrays and arrays["rgb"].ndim == 3:
        return {"": np.ascontiguousarray(arrays["rgb"][..., ::-1])}
    if output == "frame" and "recon" in arrays:
        return {
            "target": (np.clip(arrays["target"], 0, 1)[..., ::-1] * 255).astype(np.uint8),
            "recon": (np.clip(arrays["recon"], 0, 1)[..., ::-1] * 255).astype(np.uint8),
        }
    if "map" in arrays and arrays["map"].ndim == 2:
        return {"": _colour_map(arrays["map"].astype(np.float32))}
    if "anomaly" in arrays and arrays["anomaly"].ndim == 2:
        return {"anomaly": (np.where(arrays["anomaly"] == 1, 255, 0)).astype(np.uint8)}
    return {}


def compressed_image(picture: np.ndarray, stamp_ns: int, frame_id: str) -> dict:
    ok, jpeg = cv2.imencode(".jpg", picture, [cv2.IMWRITE_JPEG_QUALITY, 85])
    if not ok:
        raise ValueError(f"cannot JPEG-encode a picture of shape {picture.shape}")
    return {
        "timestamp": {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000},
        "frame_id": frame_id,
        "data": base64.b64encode(jpeg.tobytes()).decode(),
        "format": "jpeg",
    }
