"""Foxglove views of a run: what the pipeline sees, as messages of Foxglove's well-known schemas.

The recorder adds them (`FoxgloveViews`, the graph's `record_views` by default: the engine names the
class, it never imports it) on `viz/<op>/<output>[/<view>]` channels beside the exact payloads (JSON
messages, `jsonschema` schemas: the official `@foxglove/schemas` files vendored in
`foxglove_schemas/`), so a log opens in Foxglove with every view below; the layout
`foxglove_layout.json` beside this file arranges them. Replay and sweeps ignore these channels (they
are JSON, not msgpack).

  - images (`foxglove.CompressedImage`, JPEG): the camera, the world model's target and
    reconstruction, every score map colour-mapped, the anomaly truth, a frame result's boxes;
  - the lidar (`foxglove.PointCloud`) in the `ego` frame, placed at the lidar's mount;
  - the ego's pose in the `odom` frame (`foxglove.FrameTransform` odom -> ego and
    `foxglove.PoseInFrame`), dead-reckoned from the ego's speed and steering (`EgoOdometry`);
  - the route raster's outline on the ground around the ego (`foxglove.SceneUpdate`);
  - on the camera image (`foxglove.ImageAnnotations`): each mask's outline and refined score for
    every map refined with masks, and the anomaly truth's outline in another colour;
  - each score map's maximum, the frame's score (`umad.FrameScore`, ours: a number to plot).
"""

from __future__ import annotations

import base64
import bisect
import json
import math
from collections import OrderedDict
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import cv2
import numpy as np

from umad_common.dataflow.api.messages import Message
from umad_common.dataflow.record.mcap_log import LogViews, View
from umad_common.datasets.synthetic.scenario import (
    MAX_STEER_RAD,
    ROUTE_EGO_FROM_BOTTOM,
    ROUTE_PX_PER_M,
    ROUTE_SIZE,
    WHEELBASE_M,
)
from umad_common.refine import resize_nearest

SCHEMA_FOLDER = Path(__file__).with_name("foxglove_schemas")  # @foxglove/schemas' JSON schemas, as published
FRAME_SCORE_SCHEMA = {
    "title": "umad.FrameScore",
    "description": "A score map's maximum: the frame's anomaly score by that map",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "properties": {
                "sec": {"type": "integer", "minimum": 0},
                "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
            },
            "required": ["sec", "nsec"],
        },
        "run": {"type": "string", "description": "the drive"},
        "seq": {"type": "integer", "minimum": 0, "description": "the frame's index in the drive"},
        "score": {"type": "number", "description": "the map's maximum"},
        "partial": {"type": "boolean", "description": "the fused map lacked a difference map (live deadline)"},
    },
    "required": ["timestamp", "run", "seq", "score", "partial"],
}
ODOM_FRAME, EGO_FRAME = "odom", "ego"
ANOVOX_LIDAR_MOUNT = (0.0, 0.0, 1.8)  # m, CARLA axes: AnoVox's lidar, for drives without a sensor setup
FLOAT32 = 7  # foxglove.NumericType
LINE_LOOP_3D, LINE_LOOP_2D = 1, 2  # foxglove.LinePrimitive / foxglove.PointsAnnotation types
TRUTH_COLOUR = {"r": 0.1, "g": 1.0, "b": 0.3, "a": 1.0}  # the anomaly truth's outline: green, beside the masks' inferno
ROUTE_COLOUR = {"r": 0.2, "g": 0.6, "b": 1.0, "a": 1.0}
OUTLINE_TOLERANCE_PX = 0.7  # a mask's outline, simplified: no pixel of it farther off (in the mask's pixels)
LABEL_FONT_PX = 12.0
MASK_LABELS = 5  # masks whose score is written beside them, highest first (as the frame result's top_k)
MASKS_REMEMBERED = 32  # frames of masks (and of maps waiting for their masks) kept per channel for the join
INFERNO_BGR = [
    tuple(int(c) for c in bgr)
    for bgr in cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_INFERNO)[:, 0]
]


@cache
def schema(name: str) -> dict:
    """The JSON schema of a viz message: a vendored `foxglove.*` file, or ours (`umad.FrameScore`)."""
    if name == FRAME_SCORE_SCHEMA["title"]:
        return FRAME_SCORE_SCHEMA
    path = SCHEMA_FOLDER / f"{name}.json"
    if not path.is_file():
        raise ValueError(f"{name}: no such Foxglove schema in {SCHEMA_FOLDER}; expected one of {vendored_schemas()}")
    return json.loads(path.read_text())


def vendored_schemas() -> list[str]:
    return sorted(p.stem for p in SCHEMA_FOLDER.glob("foxglove.*.json"))


def _colour_map(score: np.ndarray) -> np.ndarray:
    """A [0, 1] score map as a BGR heat map."""
    lo, hi = float(np.min(score)), float(np.max(score))
    scaled = np.zeros_like(score, np.uint8) if hi <= lo else ((score - lo) / (hi - lo) * 255).astype(np.uint8)
    return cv2.applyColorMap(scaled, cv2.COLORMAP_INFERNO)


def _score_bgr(score: float) -> tuple[int, int, int]:
    """A [0, 1] score's inferno colour, BGR."""
    return INFERNO_BGR[min(255, max(0, int(score * 255)))]


def score_colour(score: float) -> dict:
    """A [0, 1] score's inferno colour as a foxglove.Color (the heat maps' colours)."""
    blue, green, red = _score_bgr(score)
    return {"r": red / 255, "g": green / 255, "b": blue / 255, "a": 1.0}


def _boxes_picture(msg: Message) -> np.ndarray:
    """A frame result's boxes on a dark canvas of the image's size: each outlined in its score's
    colour with the score beside it, the frame's score in the top-left corner."""
    boxes = msg.arrays["boxes"]
    extent = (int(boxes[:, 3].max()), int(boxes[:, 2].max())) if len(boxes) else (1, 1)
    height, width = (int(n) for n in msg.meta.get("image_size", extent))
    picture = np.zeros((height, width, 3), np.uint8)
    for (x0, y0, x1, y1), score in zip(boxes, msg.arrays["box_scores"], strict=True):
        colour = _score_bgr(float(score))
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


def _time(stamp_ns: int) -> dict:
    return {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000}


def _quaternion(roll: float, pitch: float, yaw: float) -> dict:
    """Rotation about x, then y, then z (radians, right-handed) as a foxglove.Quaternion."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return {
        "x": sr * cp * cy - cr * sp * sy,
        "y": cr * sp * cy + sr * cp * sy,
        "z": cr * cp * sy - sr * sp * cy,
        "w": cr * cp * cy + sr * sp * sy,
    }


def compressed_image(picture: np.ndarray, stamp_ns: int, frame_id: str) -> dict:
    ok, jpeg = cv2.imencode(".jpg", picture, [cv2.IMWRITE_JPEG_QUALITY, 85])
    if not ok:
        raise ValueError(f"cannot JPEG-encode a picture of shape {picture.shape}")
    return {
        "timestamp": _time(stamp_ns),
        "frame_id": frame_id,
        "data": base64.b64encode(jpeg.tobytes()).decode(),
        "format": "jpeg",
    }


def lidar_mount_pose(sensors: dict | None) -> dict:
    """The lidar's pose in the ego frame (x forward, y left, z up) from the replayer's `sensors`
    meta (CARLA axes: y right; rotation (pitch, yaw, roll) in degrees, yaw and pitch positive to the
    right and up, roll positive right side down; or a recording's `axes` matrix, the lidar's axes as
    columns in the ego frame); AnoVox's mount without one."""
    lidar = (sensors or {}).get("lidar") or {"location": ANOVOX_LIDAR_MOUNT, "rotation": (0.0, 0.0, 0.0)}
    x, y, z = (float(v) for v in lidar["location"])
    position = {"x": x, "y": -y, "z": z}
    if lidar.get("axes") is not None:
        from scipy.spatial.transform import Rotation

        qx, qy, qz, qw = Rotation.from_matrix(lidar["axes"]).as_quat()
        return {"position": position, "orientation": {"x": float(qx), "y": float(qy), "z": float(qz), "w": float(qw)}}
    pitch, yaw, roll = (math.radians(float(v)) for v in lidar.get("rotation", (0.0, 0.0, 0.0)))
    return {"position": position, "orientation": _quaternion(roll, -pitch, -yaw)}


def point_cloud(points: np.ndarray, stamp_ns: int, sensors: dict | None) -> dict:
    """(N, 4) float32 lidar points (x forward, y left, z up: the replayer's (x, -y, z), intensity)
    in the lidar's frame as a foxglove.PointCloud in the ego frame, posed at the lidar's mount."""
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"lidar points of shape {points.shape}; expected (N, 4) x, -y, z, intensity")
    data = np.ascontiguousarray(points, "<f4")
    return {
        "timestamp": _time(stamp_ns),
        "frame_id": EGO_FRAME,
        "pose": lidar_mount_pose(sensors),
        "point_stride": 16,
        "fields": [
            {"name": name, "offset": 4 * index, "type": FLOAT32}
            for index, name in enumerate(("x", "y", "z", "intensity"))
        ],
        "data": base64.b64encode(data.tobytes()).decode(),
    }


@dataclass(frozen=True)
class EgoState:
    stamp_ns: int
    x: float  # m in the odom frame
    y: float
    yaw: float  # rad, counter-clockwise from the odom frame's x
    speed: float  # m/s
    yaw_rate: float  # rad/s


class EgoOdometry:
    """The ego's pose per run, dead-reckoned from its speed and steering: the replayer publishes no
    pose, only the actions. A kinematic bicycle with the built-in world's wheelbase and steering
    range (CARLA's sign: positive steers right) turns the steering into a yaw rate; the pose moves
    on at the mean of two frames' speeds and yaw rates over their stamps' interval. Each run starts
    at the origin of `odom` facing x. A frame seen again (a re-sent frame) keeps its pose; a frame
    after a gap moves on from the newest earlier frame."""

    def __init__(self) -> None:
        self._runs: dict[str, dict[int, EgoState]] = {}
        self._seqs: dict[str, list[int]] = {}

    def pose(self, run: str, seq: int, stamp_ns: int, speed: float, steer: float) -> EgoState:
        states, seqs = self._runs.setdefault(run, {}), self._seqs.setdefault(run, [])
        if seq in states:
            return states[seq]
        yaw_rate = speed * math.tan(-steer * MAX_STEER_RAD) / WHEELBASE_M
        before = bisect.bisect_left(seqs, seq)
        if before == 0:
            state = EgoState(stamp_ns, 0.0, 0.0, 0.0, speed, yaw_rate)
        else:
            last = states[seqs[before - 1]]
            dt = max(0.0, (stamp_ns - last.stamp_ns) / 1e9)
            mean_speed, mean_yaw_rate = (last.speed + speed) / 2, (last.yaw_rate + yaw_rate) / 2
            heading = last.yaw + mean_yaw_rate * dt / 2
            state = EgoState(
                stamp_ns,
                last.x + mean_speed * math.cos(heading) * dt,
                last.y + mean_speed * math.sin(heading) * dt,
                last.yaw + mean_yaw_rate * dt,
                speed,
                yaw_rate,
            )
        states[seq] = state
        seqs.insert(before, seq)
        return state


def ego_messages(state: EgoState) -> dict[str, tuple[str, dict]]:
    """The ego's pose as a transform odom -> ego and as a pose in odom, by view name."""
    stamp = _time(state.stamp_ns)
    position = {"x": state.x, "y": state.y, "z": 0.0}
    orientation = _quaternion(0.0, 0.0, state.yaw)
    transform = {
        "timestamp": stamp,
        "parent_frame_id": ODOM_FRAME,
        "child_frame_id": EGO_FRAME,
        "translation": position,
        "rotation": orientation,
    }
    pose = {"timestamp": stamp, "frame_id": ODOM_FRAME, "pose": {"position": position, "orientation": orientation}}
    return {"transform": ("foxglove.FrameTransform", transform), "pose": ("foxglove.PoseInFrame", pose)}


def _outlines(
    mask: np.ndarray, scale_x: float, scale_y: float, offset: tuple[int, int] = (0, 0), tolerance_px: float = 0.0
) -> list[np.ndarray]:
    """The outer outlines of a (h, w) uint8 or bool mask's regions, (n, 2) float x, y in the scaled
    image's pixels (rounded to a tenth of a pixel: the JSON stays short). `offset`: the mask's
    top-left corner (x, y) in the whole image; `tolerance_px`: each outline simplified to a polygon
    that leaves none of its pixels farther than this (in the mask's pixels)."""
    contours, _ = cv2.findContours(mask.view(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE, offset=offset)
    if tolerance_px > 0:
        contours = [cv2.approxPolyDP(c, tolerance_px, True) for c in contours]
    return [np.round(c[:, 0, :] * (scale_x, scale_y), 1) for c in contours]


def route_scene(route: np.ndarray, stamp_ns: int) -> dict:
    """The route raster's outline on the ground around the ego, as a foxglove.SceneUpdate: the
    raster is the built-in world's (ROUTE_PX_PER_M px per metre, the ego ROUTE_EGO_FROM_BOTTOM px
    above the bottom edge's centre, heading up)."""
    if route.shape != (ROUTE_SIZE, ROUTE_SIZE):
        raise ValueError(f"route raster of shape {route.shape}; expected ({ROUTE_SIZE}, {ROUTE_SIZE})")
    lines = []
    for outline in _outlines(route > 0, 1.0, 1.0):
        forward = (ROUTE_SIZE - ROUTE_EGO_FROM_BOTTOM - outline[:, 1]) / ROUTE_PX_PER_M
        left = (ROUTE_SIZE / 2 - outline[:, 0]) / ROUTE_PX_PER_M
        lines.append(
            {
                "type": LINE_LOOP_3D,
                "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": _quaternion(0.0, 0.0, 0.0)},
                "thickness": 0.15,
                "scale_invariant": False,
                "points": [{"x": f, "y": s, "z": 0.05} for f, s in zip(forward.tolist(), left.tolist(), strict=True)],
                "color": ROUTE_COLOUR,
                "colors": [],
                "indices": [],
            }
        )
    entity = {
        "timestamp": _time(stamp_ns),
        "frame_id": EGO_FRAME,
        "id": "route",
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": True,
        "metadata": [],
        **{kind: [] for kind in ("arrows", "cubes", "spheres", "cylinders", "triangles", "texts", "models")},
        "lines": lines,
    }
    return {"deletions": [], "entities": [entity]}


def _outline_annotation(outline: np.ndarray, stamp: dict, colour: dict, thickness: float) -> dict:
    return {
        "timestamp": stamp,
        "type": LINE_LOOP_2D,
        "points": [{"x": x, "y": y} for x, y in outline.tolist()],
        "outline_color": colour,
        "outline_colors": [],
        "fill_color": {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.0},
        "thickness": thickness,
    }


def _label(text: str, x: float, y: float, stamp: dict, colour: dict) -> dict:
    return {
        "timestamp": stamp,
        "position": {"x": x, "y": y},
        "text": text,
        "font_size": LABEL_FONT_PX,
        "text_color": colour,
        "background_color": {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.6},
    }


def mask_annotations(refined: np.ndarray, masks: np.ndarray, camera_size: tuple[int, int], stamp_ns: int) -> dict:
    """Each non-empty mask's outline on the camera image of `camera_size` (h, w) in its refined
    score's colour (the score: the refined map's mean over the mask, as the frame result's boxes),
    the score written at the top-left corner of the MASK_LABELS highest-scoring masks, as
    foxglove.ImageAnnotations. A frame of label-free masks has a hundred or more, so each mask is
    read within its bounding box, its outlines are simplified by OUTLINE_TOLERANCE_PX, and its
    specks (regions whose outline has fewer than 3 corners: a pixel, a one-pixel line) are left out
    but for a mask that has nothing else."""
    masks = np.ascontiguousarray(resize_nearest(masks.astype(bool, copy=False), refined.shape)).view(np.uint8)
    scale_x, scale_y = camera_size[1] / refined.shape[1], camera_size[0] / refined.shape[0]
    stamp = _time(stamp_ns)
    regions_of, scores = [], []
    for mask in masks:
        x, y, width, height = cv2.boundingRect(mask)
        if width == 0:  # an empty mask
            continue
        crop = mask[y : y + height, x : x + width]
        scores.append(float(refined[y : y + height, x : x + width][crop.view(bool)].mean(dtype=np.float64)))
        regions = _outlines(crop, scale_x, scale_y, (x, y), OUTLINE_TOLERANCE_PX)
        regions_of.append([region for region in regions if len(region) >= 3] or regions[:1])
    labelled = set(np.argsort(-np.array(scores), kind="stable")[:MASK_LABELS].tolist())
    outlines, labels = [], []
    for index, (regions, score) in enumerate(zip(regions_of, scores, strict=True)):
        colour, text = score_colour(score), f"{score:.2f}"
        outlines.extend(_outline_annotation(region, stamp, colour, 2.0) for region in regions)
        if index in labelled:
            corner = np.concatenate(regions).min(axis=0)
            labels.append(_label(text, float(corner[0]), float(corner[1]), stamp, colour))
    return {"timestamp": stamp, "circles": [], "points": outlines, "texts": labels, "metadata": []}


def truth_annotations(anomaly: np.ndarray, stamp_ns: int) -> dict:
    """The anomaly truth's outlines (label 1) on the camera image, as foxglove.ImageAnnotations."""
    stamp = _time(stamp_ns)
    regions = _outlines(anomaly == 1, 1.0, 1.0)
    outlines = [_outline_annotation(region, stamp, TRUTH_COLOUR, 3.0) for region in regions]
    labels = [
        _label("anomaly", float(region[:, 0].min()), float(region[:, 1].max()) + LABEL_FONT_PX + 2, stamp, TRUTH_COLOUR)
        for region in regions
    ]
    return {"timestamp": stamp, "circles": [], "points": outlines, "texts": labels, "metadata": []}


def frame_score(msg: Message, score: float) -> dict:
    return {
        "timestamp": _time(msg.stamp_ns),
        "run": msg.run,
        "seq": msg.seq,
        "score": score,
        "partial": bool(msg.meta.get("partial", False)),
    }


class FoxgloveViews(LogViews):
    """Turns bus messages into viz messages, one message at a time, in the order they were recorded:
    the recorder's views by default (the graph's `record_views`).

    Args:
        mask_sources: map channel (`op/output`) -> the masks channel that refined it (the graph's
            wiring): each such map's masks are outlined on the camera with their refined scores,
            once the frame's map, its masks and the run's camera size are all known.
    """

    def __init__(self, mask_sources: dict[str, str] | None = None):
        self.mask_sources = dict(mask_sources or {})
        self.odometry = EgoOdometry()
        self._camera_sizes: dict[str, tuple[int, int]] = {}  # run -> camera (h, w)
        self._masks: dict[str, OrderedDict] = {}  # masks channel -> (run, seq) -> masks
        self._maps_waiting: dict[str, OrderedDict] = {}  # map channel -> (run, seq) -> (map, stamp_ns)

    def of(self, channel: str, msg: Message) -> list[View]:
        """The viz messages of one bus message on `channel` (`op/output`)."""
        arrays, output = msg.arrays, channel.rsplit("/", 1)[-1]
        frame_id = f"{msg.run}#{msg.seq}"
        found = [
            View(
                f"viz/{channel}" + (f"/{name}" if name else ""),
                "foxglove.CompressedImage",
                compressed_image(picture, msg.stamp_ns, frame_id),
            )
            for name, picture in views(output, msg).items()
        ]
        if "rgb" in arrays and arrays["rgb"].ndim == 3:
            self._camera_sizes[msg.run] = tuple(arrays["rgb"].shape[:2])
            found += self._joined_masks(msg.run)
        if "points" in arrays:
            body = point_cloud(arrays["points"], msg.stamp_ns, msg.meta.get("sensors"))
            found.append(View(f"viz/{channel}", "foxglove.PointCloud", body))
        if "ego" in arrays:
            speed, steer = float(arrays["ego"][0]), float(arrays["ego"][3])
            state = self.odometry.pose(msg.run, msg.seq, msg.stamp_ns, speed, steer)
            found += [View(f"viz/{channel}/{name}", s, body) for name, (s, body) in ego_messages(state).items()]
        if "route" in arrays:
            found.append(View(f"viz/{channel}", "foxglove.SceneUpdate", route_scene(arrays["route"], msg.stamp_ns)))
        if "anomaly" in arrays and arrays["anomaly"].ndim == 2:
            body = truth_annotations(arrays["anomaly"], msg.stamp_ns)
            found.append(View(f"viz/{channel}/annotations", "foxglove.ImageAnnotations", body))
        if "map" in arrays and arrays["map"].ndim == 2:
            score = float(arrays["map"].max()) if arrays["map"].size else 0.0
            found.append(View(f"viz/{channel}/score", FRAME_SCORE_SCHEMA["title"], frame_score(msg, score)))
            if channel in self.mask_sources:
                found += self._map_with_masks(channel, msg)
        elif "score" in arrays and "boxes" in arrays:  # a frame result
            body = frame_score(msg, float(arrays["score"][0]))
            found.append(View(f"viz/{channel}/score", FRAME_SCORE_SCHEMA["title"], body))
        if "masks" in arrays and arrays["masks"].ndim == 3 and channel in self.mask_sources.values():
            _remember(self._masks.setdefault(channel, OrderedDict()), (msg.run, msg.seq), arrays["masks"])
            found += self._joined_masks(msg.run)
        return found

    def schema(self, name: str) -> dict:
        return schema(name)

    def _map_with_masks(self, channel: str, msg: Message) -> list[View]:
        waiting = self._maps_waiting.setdefault(channel, OrderedDict())
        _remember(waiting, (msg.run, msg.seq), (msg.arrays["map"], msg.stamp_ns))
        return self._joined_masks(msg.run)

    def _joined_masks(self, run: str) -> list[View]:
        """Mask annotations of every waiting map of `run` whose masks and camera size are known."""
        camera_size = self._camera_sizes.get(run)
        if camera_size is None:
            return []
        found = []
        for channel, waiting in self._maps_waiting.items():
            masks_of = self._masks.get(self.mask_sources[channel], {})
            for frame in [f for f in waiting if f[0] == run and f in masks_of]:
                refined, stamp_ns = waiting.pop(frame)
                body = mask_annotations(refined, masks_of[frame], camera_size, stamp_ns)
                found.append(View(f"viz/{channel}/masks", "foxglove.ImageAnnotations", body))
        return found


def _remember(cache: OrderedDict, frame: tuple[str, int], value: object) -> None:
    cache[frame] = value
    cache.move_to_end(frame)
    while len(cache) > MASKS_REMEMBERED:
        cache.popitem(last=False)
