"""Decoded recording messages -> arrays: the camera, lidar, ego, labels and rig of ROS 2 and Foxglove
messages.

The messages come decoded by the libraries that own their formats (rosbags and mcap-ros2-support for
ROS 2 CDR, mcap-protobuf-support for protobuf, `json` for JSON, see
`umad_common.datasets.recording`); this module only reads their fields by name. ROS 2 type names are
written `pkg/msg/Name`, Foxglove's `foxglove.Name`.

Axes: ROS (REP 103) and Foxglove put x forward, y left, z up, the replayer's lidar convention.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np

from umad_common.datasets.drive import DatasetError

ROS_IMAGE = "sensor_msgs/msg/Image"
ROS_COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
FOXGLOVE_RAW_IMAGE = "foxglove.RawImage"
FOXGLOVE_COMPRESSED_IMAGE = "foxglove.CompressedImage"
IMAGE_TYPES = (ROS_IMAGE, ROS_COMPRESSED_IMAGE, FOXGLOVE_RAW_IMAGE, FOXGLOVE_COMPRESSED_IMAGE)
CLOUD_TYPES = ("sensor_msgs/msg/PointCloud2", "foxglove.PointCloud")
ODOMETRY_TYPES = ("nav_msgs/msg/Odometry", "foxglove.PoseInFrame")
CONTROL_TYPES = ("carla_msgs/msg/CarlaEgoVehicleControl", "ackermann_msgs/msg/AckermannDriveStamped")
CAMERA_INFO_TYPES = ("sensor_msgs/msg/CameraInfo", "foxglove.CameraCalibration")
TRANSFORM_TYPES = ("tf2_msgs/msg/TFMessage", "foxglove.FrameTransform", "foxglove.FrameTransforms")

# Message definitions of the control types, which ROS distributions do not ship: a bag whose storage
# embeds no definitions (older SQLite3 bags) is read with these.
EXTRA_DEFINITIONS = {
    "carla_msgs/msg/CarlaEgoVehicleControl": "std_msgs/Header header\nfloat32 throttle\nfloat32 steer\n"
    "float32 brake\nbool hand_brake\nbool reverse\nint32 gear\nbool manual_gear_shift\n",
    "ackermann_msgs/msg/AckermannDrive": "float32 steering_angle\nfloat32 steering_angle_velocity\nfloat32 speed\n"
    "float32 acceleration\nfloat32 jerk\n",
    "ackermann_msgs/msg/AckermannDriveStamped": "std_msgs/Header header\nackermann_msgs/AckermannDrive drive\n",
}

IMAGE_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8uc1": 1}
# PointCloud2 PointField datatypes and Foxglove NumericType values -> little-endian numpy types.
ROS_FIELD_TYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
FOXGLOVE_FIELD_TYPES = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<f4", 8: "<f8"}
FOXGLOVE_FIELD_NAMES = {
    "UINT8": 1, "INT8": 2, "UINT16": 3, "INT16": 4, "UINT32": 5, "INT32": 6, "FLOAT32": 7, "FLOAT64": 8,
}  # fmt: skip


def canonical_type(name: str) -> str:
    """`sensor_msgs/Image` and `sensor_msgs/msg/Image` -> `sensor_msgs/msg/Image`; other names unchanged."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def from_json(payload: bytes) -> SimpleNamespace:
    """A JSON-encoded message as nested attributes, like the other decoders give."""
    import json

    def to_namespace(value: Any) -> Any:
        if isinstance(value, dict):
            return SimpleNamespace(**{k: to_namespace(v) for k, v in value.items()})
        if isinstance(value, list):
            return [to_namespace(v) for v in value]
        return value

    return to_namespace(json.loads(payload))


def as_bytes(data: Any) -> np.ndarray:
    """A message's byte array (bytes, a numpy array, a list, or base64 text in JSON) as uint8."""
    if isinstance(data, str):
        return np.frombuffer(base64.b64decode(data), np.uint8)
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1)
    if isinstance(data, bytes | bytearray | memoryview):
        return np.frombuffer(data, np.uint8)
    return np.asarray(data, np.uint8)


def stamp_of(msg: Any) -> int | None:
    """A message's own time in ns (header.stamp or Foxglove's timestamp), None if it has none."""
    stamp = getattr(getattr(msg, "header", None), "stamp", None) or getattr(msg, "timestamp", None)
    if stamp is None:
        return None
    seconds = getattr(stamp, "sec", getattr(stamp, "seconds", 0))
    nanos = getattr(stamp, "nanosec", getattr(stamp, "nsec", getattr(stamp, "nanos", 0)))
    return int(seconds) * 1_000_000_000 + int(nanos)


def frame_id_of(msg: Any) -> str:
    """The coordinate frame a message is in (ROS header.frame_id, Foxglove frame_id)."""
    header = getattr(msg, "header", None)
    return str(getattr(header, "frame_id", "") if header is not None else getattr(msg, "frame_id", ""))


def image_pixels(msg: Any, type_name: str, where: str) -> np.ndarray:
    """An image message -> (H, W, C) uint8 in RGB order (C = 3), or (H, W, 1) for mono8."""
    if type_name in (ROS_COMPRESSED_IMAGE, FOXGLOVE_COMPRESSED_IMAGE):
        fmt = str(msg.format).lower()
        if not any(name in fmt for name in ("jpeg", "jpg", "png")):
            raise DatasetError(f"{where}: compressed image format {msg.format!r}; expected jpeg or png")
        image = cv2.imdecode(as_bytes(msg.data), cv2.IMREAD_UNCHANGED)
        if image is None or image.dtype != np.uint8:
            raise DatasetError(f"{where}: a {msg.format} image that cannot be decoded to 8 bits; expected jpeg or png")
        if image.ndim == 2:
            return image[..., None]
        return np.ascontiguousarray(image[..., 2::-1])
    encoding = str(msg.encoding).lower()
    if encoding not in IMAGE_CHANNELS:
        raise DatasetError(
            f"{where}: image encoding {msg.encoding!r} is not supported; expected one of rgb8, bgr8, rgba8, bgra8, mono8"
        )
    channels = IMAGE_CHANNELS[encoding]
    height, width = int(msg.height), int(msg.width)
    step = int(msg.step) or width * channels
    data = as_bytes(msg.data)
    if step < width * channels or len(data) < step * height:
        raise DatasetError(
            f"{where}: {encoding} image of {width}x{height} with step {step} holds {len(data)} bytes; "
            f"expected step >= {width * channels} and {step * height} bytes"
        )
    rows = data[: step * height].reshape(height, step)[:, : width * channels].reshape(height, width, channels)
    if encoding in ("rgb8", "rgba8"):
        return np.ascontiguousarray(rows[..., :3])
    if encoding in ("bgr8", "bgra8"):
        return np.ascontiguousarray(rows[..., 2::-1])
    return np.ascontiguousarray(rows)


def camera_rgb(msg: Any, type_name: str, where: str) -> np.ndarray:
    """A camera image -> (H, W, 3) uint8 RGB (a mono8 image as grey in all three)."""
    pixels = image_pixels(msg, type_name, where)
    return np.repeat(pixels, 3, axis=2) if pixels.shape[2] == 1 else pixels


def label_mask(msg: Any, type_name: str, where: str) -> np.ndarray:
    """A labels image (mono8, nonzero = anomaly) -> (H, W) uint8 0/1."""
    pixels = image_pixels(msg, type_name, where)
    if pixels.shape[2] != 1:
        raise DatasetError(f"{where}: labels image has {pixels.shape[2]} channels; expected mono8, nonzero = anomaly")
    return (pixels[..., 0] != 0).astype(np.uint8)


def cloud_points(msg: Any, type_name: str, where: str) -> np.ndarray:
    """A point cloud -> (N, 4) float32 (x, y, z, intensity; intensity 0 where the cloud has none), read
    by field name and offset with the cloud's own point step; points with a NaN or infinite coordinate
    are dropped. A Foxglove cloud's pose is applied, so the points are in its frame_id."""
    foxglove = type_name == "foxglove.PointCloud"
    if not foxglove and bool(msg.is_bigendian):
        raise DatasetError(f"{where}: a big-endian point cloud; expected a little-endian one (is_bigendian false)")
    step = int(msg.point_stride if foxglove else msg.point_step)
    data = as_bytes(msg.data)
    count = len(data) // step if foxglove and step else int(msg.width) * int(msg.height)
    if step <= 0 or len(data) < count * step:
        raise DatasetError(f"{where}: cloud of {count} points of {step} bytes holds {len(data)} bytes")
    types = FOXGLOVE_FIELD_TYPES if foxglove else ROS_FIELD_TYPES
    fields = {}
    for field in msg.fields:
        kind = field.type if foxglove else field.datatype
        kind = FOXGLOVE_FIELD_NAMES.get(kind, 0) if isinstance(kind, str) else int(kind)
        fields[str(field.name)] = (int(field.offset), types.get(kind))
    missing = [axis for axis in ("x", "y", "z") if axis not in fields or fields[axis][1] not in ("<f4", "<f8")]
    if missing:
        raise DatasetError(
            f"{where}: cloud fields {sorted(fields)} lack float x, y, z ({', '.join(missing)}); "
            "expected float32 fields x, y, z (and intensity)"
        )
    names = ["x", "y", "z"] + (["intensity"] if fields.get("intensity", (0, None))[1] else [])
    dtype = np.dtype(
        {
            "names": names,
            "formats": [fields[n][1] for n in names],
            "offsets": [fields[n][0] for n in names],
            "itemsize": step,
        }
    )
    table = np.frombuffer(np.ascontiguousarray(data[: count * step]), dtype)
    points = np.zeros((count, 4), np.float32)
    for column, name in enumerate(names):
        points[:, column] = table[name]
    if foxglove and getattr(msg, "pose", None) is not None:
        rotation, translation = pose_matrix(msg.pose)
        points[:, :3] = (points[:, :3].astype(np.float64) @ rotation.T + translation).astype(np.float32)
    return points[np.isfinite(points[:, :3]).all(axis=1)]


def vector(value: Any) -> np.ndarray:
    return np.array([float(getattr(value, axis, 0.0)) for axis in ("x", "y", "z")])


def quaternion_matrix(q: Any) -> np.ndarray:
    """A quaternion (x, y, z, w attributes; all zero reads as identity) -> 3x3 rotation matrix."""
    from scipy.spatial.transform import Rotation

    xyzw = [float(getattr(q, axis, 0.0)) for axis in ("x", "y", "z", "w")] if q is not None else [0, 0, 0, 1]
    if not any(xyzw):
        return np.eye(3)
    return Rotation.from_quat(xyzw).as_matrix()


def pose_matrix(pose: Any) -> tuple[np.ndarray, np.ndarray]:
    """A pose (position, orientation) -> (3x3 rotation, translation)."""
    return quaternion_matrix(getattr(pose, "orientation", None)), vector(getattr(pose, "position", None))


@dataclass(frozen=True)
class Transform:
    """Where frame `child` sits in frame `parent`: p_parent = rotation @ p_child + translation."""

    parent: str
    child: str
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)


def transforms_of(msg: Any, type_name: str) -> list[Transform]:
    """The transforms a tf2 TFMessage or a Foxglove FrameTransform(s) message holds."""
    if type_name == "tf2_msgs/msg/TFMessage":
        return [
            Transform(
                str(t.header.frame_id).lstrip("/"),
                str(t.child_frame_id).lstrip("/"),
                quaternion_matrix(t.transform.rotation),
                vector(t.transform.translation),
            )
            for t in msg.transforms
        ]
    items = msg.transforms if type_name == "foxglove.FrameTransforms" else [msg]
    return [
        Transform(
            str(t.parent_frame_id).lstrip("/"),
            str(t.child_frame_id).lstrip("/"),
            quaternion_matrix(t.rotation),
            vector(t.translation),
        )
        for t in items
    ]


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera's image size and its K matrix's entries (pixels)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


def intrinsics_of(msg: Any, type_name: str, where: str) -> Intrinsics:
    """A CameraInfo or Foxglove CameraCalibration -> its image size and focal lengths and centre."""
    k = [float(v) for v in (getattr(msg, "k", None) if type_name == "sensor_msgs/msg/CameraInfo" else msg.K)]
    if len(k) != 9 or k[0] <= 0 or k[4] <= 0:
        raise DatasetError(f"{where}: camera matrix K {k}; expected 9 values with fx, fy > 0")
    return Intrinsics(int(msg.width), int(msg.height), k[0], k[4], k[2], k[5])


@dataclass(frozen=True)
class OdometrySample:
    """The ego's motion at one time: speed (m/s, None for a pose) and yaw rate (rad/s, left positive),
    or its planar pose (x, y, heading) where the message holds only a pose."""

    speed: float | None
    yaw_rate: float | None
    pose: tuple[float, float, float] | None = None


def odometry_of(msg: Any, type_name: str) -> OdometrySample:
    """nav_msgs/Odometry: speed = |twist.linear|, yaw rate = twist.angular.z; Foxglove PoseInFrame:
    the pose, differenced over time by the reader."""
    if type_name == "nav_msgs/msg/Odometry":
        twist = msg.twist.twist
        return OdometrySample(float(np.linalg.norm(vector(twist.linear))), float(twist.angular.z))
    rotation, translation = pose_matrix(msg.pose)
    return OdometrySample(
        None, None, (translation[0], translation[1], float(np.arctan2(rotation[1, 0], rotation[0, 0])))
    )


@dataclass(frozen=True)
class ControlSample:
    """The driver's command (CARLA ranges: throttle, brake in [0, 1], steer in [-1, 1], right positive)
    and, for Ackermann commands, the commanded speed (m/s)."""

    throttle: float
    brake: float
    steer: float
    speed: float | None = None


def control_of(msg: Any, type_name: str) -> ControlSample:
    """CarlaEgoVehicleControl as it is; AckermannDriveStamped converted with the synthetic world's
    vehicle (docs/design.md: steer = -steering_angle / max steering angle, acceleration split into
    throttle and brake by the full-throttle and full-brake accelerations)."""
    from umad_common.datasets.synthetic.scenario import MAX_ACCEL, MAX_DECEL, MAX_STEER_RAD

    if type_name == "carla_msgs/msg/CarlaEgoVehicleControl":
        return ControlSample(float(msg.throttle), float(msg.brake), float(msg.steer))
    drive = msg.drive
    acceleration = float(drive.acceleration)
    return ControlSample(
        float(np.clip(acceleration / MAX_ACCEL, 0.0, 1.0)),
        float(np.clip(-acceleration / MAX_DECEL, 0.0, 1.0)),
        float(np.clip(-float(drive.steering_angle) / MAX_STEER_RAD, -1.0, 1.0)),
        float(drive.speed),
    )
