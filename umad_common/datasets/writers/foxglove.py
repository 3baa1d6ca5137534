"""A drive as an MCAP file of Foxglove schemas (`write_foxglove_mcap`), protobuf or JSON encoded.
Topics, frames and times: the package's docstring."""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from umad_common.datasets.writers import (
    BASE_FRAME,
    CAMERA_FRAME,
    CLOUD_FIELDS,
    COMPRESSED_FORMATS,
    COMPRESSIONS,
    FLOAT32,
    FOXGLOVE_JSON_SCHEMAS,
    IDENTITY_ROTATION,
    LIDAR_FRAME,
    ODOM_FRAME,
    PERIOD_NS,
    START_NS,
    DeadReckoning,
    Rig,
    Stamped,
    check_choice,
    check_size,
    cloud_bytes,
    compressed_image,
    label_mask,
    scheduled,
)

if TYPE_CHECKING:
    from umad_common.datasets.drive import Drive


class FoxgloveMessages:
    """A drive's messages of Foxglove schemas as dicts in Foxglove's field names: times in ns under
    `timestamp`, byte fields as bytes (see `_json_body` and `_protobuf_body` for the encodings)."""

    def __init__(self, drive: Drive, *, image: str, labels: bool, lidar: bool, rig: bool, period_ns: int):
        check_choice("image", image, ("raw", *COMPRESSED_FORMATS))
        self.drive, self.image, self.labels, self.lidar, self.rig = drive, image, labels, lidar, rig
        self.camera = Rig.of(drive)
        self.odometry = DeadReckoning(period_ns)

    def static(self, time_ns: int) -> list[Stamped]:
        """The rig's transforms (/tf), if `rig`."""
        if not self.rig:
            return []
        transforms = [
            {
                "timestamp": time_ns,
                "parent_frame_id": BASE_FRAME,
                "child_frame_id": child,
                "translation": dict(zip("xyz", translation, strict=True)),
                "rotation": dict(zip("xyzw", rotation, strict=True)),
            }
            for child, translation, rotation in self.camera.transforms()
        ]
        return [Stamped(time_ns, "/tf", "foxglove.FrameTransforms", {"transforms": transforms})]

    def frame(self, frame: Any, times: dict[str, int]) -> list[Stamped]:
        """One frame's messages, each at its role's time."""
        check_size(self.camera, frame, self.drive.name)
        at, rig = times["camera"], self.camera
        messages = []
        if self.rig:
            calibration = {
                "timestamp": at,
                "frame_id": CAMERA_FRAME,
                "width": rig.width,
                "height": rig.height,
                "distortion_model": "plumb_bob",
                "D": [0.0] * 5,
                "K": rig.k,
                "R": np.eye(3).reshape(-1).tolist(),
                "P": rig.p,
            }
            messages.append(Stamped(at, "/camera/calibration", "foxglove.CameraCalibration", calibration))
        if self.image == "raw":
            messages.append(Stamped(at, "/camera/image", "foxglove.RawImage", _raw_image(frame.rgb, "rgb8", at)))
        else:
            compressed = {
                "timestamp": at,
                "frame_id": CAMERA_FRAME,
                "data": compressed_image(frame.rgb, self.image),
                "format": self.image,
            }
            messages.append(Stamped(at, "/camera/image", "foxglove.CompressedImage", compressed))
        if self.labels:
            mask = _raw_image(label_mask(frame, self.drive.name), "mono8", at)
            messages.append(Stamped(at, "/labels", "foxglove.RawImage", mask))
        if self.lidar and frame.lidar is not None:
            cloud = {
                "timestamp": times["lidar"],
                "frame_id": LIDAR_FRAME,
                "pose": {
                    "position": {"x": 0.0, "y": 0.0, "z": 0.0},
                    "orientation": dict(zip("xyzw", IDENTITY_ROTATION, strict=True)),
                },
                "point_stride": 16,
                "fields": [
                    {"name": name, "offset": 4 * index, "type": FLOAT32} for index, name in enumerate(CLOUD_FIELDS)
                ],
                "data": cloud_bytes(frame.lidar, 0).tobytes(),
            }
            messages.append(Stamped(times["lidar"], "/lidar/points", "foxglove.PointCloud", cloud))
        x, y, yaw = self.odometry.advance(frame.ego.speed_mps, frame.ego.steer)
        pose = {
            "timestamp": times["odometry"],
            "frame_id": ODOM_FRAME,
            "pose": {
                "position": {"x": x, "y": y, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)},
            },
        }
        messages.append(Stamped(times["odometry"], "/ego/pose", "foxglove.PoseInFrame", pose))
        return messages


def _raw_image(pixels: np.ndarray, encoding: str, time_ns: int) -> dict:
    """(H, W, channels) uint8 pixels as a foxglove.RawImage dict."""
    height, width, channels = pixels.shape
    return {
        "timestamp": time_ns,
        "frame_id": CAMERA_FRAME,
        "width": width,
        "height": height,
        "encoding": encoding,
        "step": width * channels,
        "data": np.ascontiguousarray(pixels).tobytes(),
    }


def _json_body(value: Any, key: str = "") -> Any:
    """A Foxglove dict in Foxglove's JSON encoding: times as {sec, nsec}, bytes as base64 text."""
    if key == "timestamp":
        return {"sec": value // 10**9, "nsec": value % 10**9}
    if isinstance(value, dict):
        return {k: _json_body(v, k) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_body(item) for item in value]
    if isinstance(value, bytes):
        return base64.b64encode(value).decode("ascii")
    return value


def _protobuf_body(value: Any, key: str = "") -> Any:
    """A Foxglove dict as protobuf constructor arguments: times as google.protobuf.Timestamp fields."""
    if key == "timestamp":
        return {"seconds": value // 10**9, "nanos": value % 10**9}
    if isinstance(value, dict):
        return {k: _protobuf_body(v, k) for k, v in value.items()}
    if isinstance(value, list):
        return [_protobuf_body(item) for item in value]
    return value


def foxglove_json_schema(type_name: str) -> dict:
    """The JSON schema of a Foxglove type: the vendored `@foxglove/schemas` file where there is one
    (FrameTransforms: an array of the vendored FrameTransform), else an untyped object with its title."""
    path = FOXGLOVE_JSON_SCHEMAS / f"{type_name}.json"
    if path.is_file():
        return json.loads(path.read_text())
    if type_name == "foxglove.FrameTransforms":
        transform = foxglove_json_schema("foxglove.FrameTransform")
        return {
            "title": type_name,
            "description": "An array of FrameTransform messages",
            "type": "object",
            "properties": {"transforms": {"type": "array", "items": transform}},
        }
    return {"title": type_name, "type": "object"}


def write_foxglove_mcap(
    drive: Drive,
    out_file: Path,
    *,
    encoding: str = "protobuf",
    image: str = "raw",
    compression: str = "zstd",
    labels: bool = True,
    lidar: bool = True,
    rig: bool = True,
    start_ns: int = START_NS,
    period_ns: int = PERIOD_NS,
    offsets_ns: dict[str, int] | None = None,
    max_frames: int | None = None,
) -> Path:
    """Write a drive as one MCAP file of Foxglove schemas, as Foxglove's SDKs record.

    Args:
        drive: the drive (see the module docstring).
        out_file: the .mcap file to create; it must not exist.
        encoding: `protobuf` (foxglove-schemas-protobuf's classes, with mcap-protobuf-support's writer)
            or `json` (`jsonschema` schemas, see `foxglove_json_schema`).
        image: the camera as a RawImage (`raw`, rgb8) or a CompressedImage (`jpeg`, `png`).
        compression: the chunks' compression, `zstd`, `lz4` or `none`.
        labels: write `/labels`.
        lidar: write `/lidar/points` (frames without a cloud have none).
        rig: write `/tf` and `/camera/calibration`.
        start_ns, period_ns, offsets_ns, max_frames: as for `write_rosbag2` (`/ego/pose` is the
            `odometry` role; the `control` role has no topic here).

    Returns:
        The file.

    Raises:
        ValueError: an option out of its choices, a frame whose arrays have the wrong shape or size, or
            sensors that give no rig (SensorSetupError).
        FileExistsError: `out_file` exists already.
    """
    from mcap.writer import CompressionType

    check_choice("encoding", encoding, ("protobuf", "json"))
    check_choice("compression", compression, COMPRESSIONS)
    source = FoxgloveMessages(drive, image=image, labels=labels, lidar=lidar, rig=rig, period_ns=period_ns)
    messages = scheduled(drive, source, start_ns, period_ns, offsets_ns, max_frames)
    chunk_compression = CompressionType[compression.upper()]
    with open(out_file, "xb") as stream:
        if encoding == "protobuf":
            _write_protobuf(stream, messages, chunk_compression)
        else:
            _write_json(stream, messages, chunk_compression)
    return out_file


def _write_protobuf(stream: Any, messages: Iterable[Stamped], compression: Any) -> None:
    import importlib

    from mcap_protobuf.writer import Writer

    classes = {}
    with Writer(stream, compression=compression) as writer:
        for message in messages:
            if message.type_name not in classes:
                name = message.type_name.removeprefix("foxglove.")
                module = importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2")
                classes[message.type_name] = getattr(module, name)
            body = classes[message.type_name](**_protobuf_body(message.body))
            writer.write_message(message.topic, body, log_time=message.time_ns, publish_time=message.time_ns)


def _write_json(stream: Any, messages: Iterable[Stamped], compression: Any) -> None:
    from mcap.writer import Writer

    writer = Writer(stream, compression=compression)
    writer.start(profile="", library="umad datasets.writers")
    schemas: dict[str, int] = {}
    channels: dict[str, int] = {}
    for message in messages:
        if message.type_name not in schemas:
            schema = json.dumps(foxglove_json_schema(message.type_name)).encode()
            schemas[message.type_name] = writer.register_schema(message.type_name, "jsonschema", schema)
        if message.topic not in channels:
            channels[message.topic] = writer.register_channel(message.topic, "json", schemas[message.type_name])
        writer.add_message(
            channels[message.topic],
            log_time=message.time_ns,
            data=json.dumps(_json_body(message.body)).encode(),
            publish_time=message.time_ns,
        )
    writer.finish()
