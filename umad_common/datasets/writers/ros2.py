"""A drive as a ROS 2 bag (`write_rosbag2`, rosbags) or as one bare ROS 2 MCAP file (`write_ros2_mcap`,
mcap-ros2-support), from the same messages (`ros_messages`). Topics, frames and times: the package's
docstring."""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from umad_common.datasets.recording_stores import ros_typestore
from umad_common.datasets.synthetic.scenario import MAX_ACCEL, MAX_DECEL, MAX_STEER_RAD, WHEELBASE_M
from umad_common.datasets.writers import (
    BASE_FRAME,
    CAMERA_FRAME,
    CLOUD_FIELDS,
    COMPRESSED_FORMATS,
    COMPRESSIONS,
    FLOAT32,
    IDENTITY_ROTATION,
    IMAGE_CHANNELS,
    LIDAR_FRAME,
    ODOM_FRAME,
    PERIOD_NS,
    ROS_CONTROL_TYPES,
    START_NS,
    Rig,
    Stamped,
    check_choice,
    check_size,
    cloud_bytes,
    compressed_image,
    image_pixels,
    label_mask,
    scheduled,
)

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

    from umad_common.datasets.drive import Drive


class RosMessages:
    """A drive's ROS 2 messages as rosbags message objects (see the module docstring for the topics)."""

    def __init__(
        self,
        drive: Drive,
        typestore: Typestore,
        *,
        image_encoding: str,
        labels: bool,
        control: str | None,
        lidar: bool,
        odometry: bool,
        rig: bool,
        cloud_padding: int,
    ):
        check_choice("image_encoding", image_encoding, (*IMAGE_CHANNELS, *COMPRESSED_FORMATS))
        check_choice("control", control, (*ROS_CONTROL_TYPES, None))
        if cloud_padding < 0:
            raise ValueError(f"cloud_padding = {cloud_padding}; expected 0 or more bytes after each point")
        self.types = typestore.types
        self.drive, self.image_encoding, self.labels, self.control = drive, image_encoding, labels, control
        self.lidar, self.odometry, self.rig, self.cloud_padding = lidar, odometry, rig, cloud_padding
        self.camera = Rig.of(drive)

    def _header(self, time_ns: int, frame_id: str) -> Any:
        stamp = self.types["builtin_interfaces/msg/Time"](sec=time_ns // 10**9, nanosec=time_ns % 10**9)
        return self.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def _vector(self, values: Iterable[float]) -> Any:
        return self.types["geometry_msgs/msg/Vector3"](*values)

    def _quaternion(self, values: Iterable[float]) -> Any:
        return self.types["geometry_msgs/msg/Quaternion"](*values)

    def static(self, time_ns: int) -> list[Stamped]:
        """The rig's transforms (/tf_static), if `rig`."""
        if not self.rig:
            return []
        t = self.types
        transforms = [
            t["geometry_msgs/msg/TransformStamped"](
                header=self._header(time_ns, BASE_FRAME),
                child_frame_id=child,
                transform=t["geometry_msgs/msg/Transform"](self._vector(translation), self._quaternion(rotation)),
            )
            for child, translation, rotation in self.camera.transforms()
        ]
        message = t["tf2_msgs/msg/TFMessage"](transforms=transforms)
        return [Stamped(time_ns, "/tf_static", "tf2_msgs/msg/TFMessage", message)]

    def frame(self, frame: Any, times: dict[str, int]) -> list[Stamped]:
        """One frame's messages, each at its role's time."""
        check_size(self.camera, frame, self.drive.name)
        t, at = self.types, times["camera"]
        messages = []
        if self.rig:
            messages.append(Stamped(at, "/camera/camera_info", "sensor_msgs/msg/CameraInfo", self._camera_info(at)))
        messages.append(self._image(frame.rgb, at))
        if self.labels:
            mask = self._raw_image(label_mask(frame, self.drive.name), "mono8", at)
            messages.append(Stamped(at, "/labels", "sensor_msgs/msg/Image", mask))
        if self.lidar and frame.lidar is not None:
            messages.append(self._cloud(frame.lidar, times["lidar"]))
        if self.odometry:
            messages.append(self._odometry(frame.ego.speed_mps, frame.ego.steer, times["odometry"]))
        if self.control == "carla":
            ego, header = frame.ego, self._header(times["control"], BASE_FRAME)
            message = t[ROS_CONTROL_TYPES["carla"]](
                header=header,
                throttle=ego.throttle,
                steer=ego.steer,
                brake=ego.brake,
                hand_brake=False,
                reverse=False,
                gear=0,
                manual_gear_shift=False,
            )
            messages.append(Stamped(times["control"], "/control", ROS_CONTROL_TYPES["carla"], message))
        elif self.control == "ackermann":
            ego, header = frame.ego, self._header(times["control"], BASE_FRAME)
            command = t["ackermann_msgs/msg/AckermannDrive"](
                steering_angle=-ego.steer * MAX_STEER_RAD,
                steering_angle_velocity=0.0,
                speed=ego.speed_mps,
                acceleration=ego.throttle * MAX_ACCEL - ego.brake * MAX_DECEL,
                jerk=0.0,
            )
            message = t[ROS_CONTROL_TYPES["ackermann"]](header=header, drive=command)
            messages.append(Stamped(times["control"], "/control", ROS_CONTROL_TYPES["ackermann"], message))
        return messages

    def _camera_info(self, time_ns: int) -> Any:
        rig, t = self.camera, self.types
        return t["sensor_msgs/msg/CameraInfo"](
            header=self._header(time_ns, CAMERA_FRAME),
            height=rig.height,
            width=rig.width,
            distortion_model="plumb_bob",
            d=np.zeros(5),
            k=np.array(rig.k),
            r=np.eye(3).reshape(-1),
            p=np.array(rig.p),
            binning_x=0,
            binning_y=0,
            roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        )

    def _raw_image(self, pixels: np.ndarray, encoding: str, time_ns: int) -> Any:
        height, width, channels = pixels.shape
        return self.types["sensor_msgs/msg/Image"](
            header=self._header(time_ns, CAMERA_FRAME),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=width * channels,
            data=pixels.reshape(-1),
        )

    def _image(self, rgb: np.ndarray, time_ns: int) -> Stamped:
        if self.image_encoding in COMPRESSED_FORMATS:
            data = np.frombuffer(compressed_image(rgb, self.image_encoding), np.uint8)
            message = self.types["sensor_msgs/msg/CompressedImage"](
                header=self._header(time_ns, CAMERA_FRAME), format=self.image_encoding, data=data
            )
            return Stamped(time_ns, "/camera/image_raw/compressed", "sensor_msgs/msg/CompressedImage", message)
        message = self._raw_image(image_pixels(rgb, self.image_encoding), self.image_encoding, time_ns)
        return Stamped(time_ns, "/camera/image_raw", "sensor_msgs/msg/Image", message)

    def _cloud(self, points: np.ndarray, time_ns: int) -> Stamped:
        point_step = 16 + self.cloud_padding
        message = self.types["sensor_msgs/msg/PointCloud2"](
            header=self._header(time_ns, LIDAR_FRAME),
            height=1,
            width=len(points),
            fields=[
                self.types["sensor_msgs/msg/PointField"](name=name, offset=4 * index, datatype=FLOAT32, count=1)
                for index, name in enumerate(CLOUD_FIELDS)
            ],
            is_bigendian=False,
            point_step=point_step,
            row_step=point_step * len(points),
            data=cloud_bytes(points, self.cloud_padding),
            is_dense=True,
        )
        return Stamped(time_ns, "/lidar/points", "sensor_msgs/msg/PointCloud2", message)

    def _odometry(self, speed_mps: float, steer: float, time_ns: int) -> Stamped:
        """The speed as twist.linear.x and the yaw rate of `DeadReckoning`'s bicycle as twist.angular.z."""
        t = self.types
        yaw_rate = speed_mps * math.tan(-steer * MAX_STEER_RAD) / WHEELBASE_M
        pose = t["geometry_msgs/msg/Pose"](
            t["geometry_msgs/msg/Point"](0.0, 0.0, 0.0), self._quaternion(IDENTITY_ROTATION)
        )
        twist = t["geometry_msgs/msg/Twist"](self._vector((speed_mps, 0.0, 0.0)), self._vector((0.0, 0.0, yaw_rate)))
        message = t["nav_msgs/msg/Odometry"](
            header=self._header(time_ns, ODOM_FRAME),
            child_frame_id=BASE_FRAME,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose, np.zeros(36)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist, np.zeros(36)),
        )
        return Stamped(time_ns, "/odom", "nav_msgs/msg/Odometry", message)


def ros_messages(
    drive: Drive,
    typestore: Typestore,
    *,
    image_encoding: str = "rgb8",
    labels: bool = True,
    control: str | None = "carla",
    lidar: bool = True,
    odometry: bool = True,
    rig: bool = True,
    cloud_padding: int = 0,
    start_ns: int = START_NS,
    period_ns: int = PERIOD_NS,
    offsets_ns: dict[str, int] | None = None,
    max_frames: int | None = None,
) -> Iterator[Stamped]:
    """A drive's ROS 2 messages (see the module docstring for the topics) in log-time order.

    Args:
        drive: the drive (see the module docstring).
        typestore: the rosbags typestore of the message types.
        image_encoding: the camera as a raw Image (`rgb8`, `bgr8`, `rgba8`, `bgra8`, `mono8`) or a
            CompressedImage (`jpeg`, `png`).
        labels: write `/labels`.
        control: `/control` as `carla` or `ackermann` commands, or None for none.
        lidar: write `/lidar/points` (frames without a cloud have none).
        odometry: write `/odom`.
        rig: write `/tf_static` and `/camera/camera_info`.
        cloud_padding: bytes after each point's four floats (point_step = 16 + cloud_padding).
        start_ns: the time of frame 0.
        period_ns: the time between frames.
        offsets_ns: role (of ROLES) -> offset of its messages from the frame's time.
        max_frames: write only the first frames.

    Raises:
        ValueError: an option out of its choices, or timing that cannot be (see `scheduled`).
    """
    source = RosMessages(
        drive,
        typestore,
        image_encoding=image_encoding,
        labels=labels,
        control=control,
        lidar=lidar,
        odometry=odometry,
        rig=rig,
        cloud_padding=cloud_padding,
    )
    return scheduled(drive, source, start_ns, period_ns, offsets_ns, max_frames)


def write_rosbag2(
    drive: Drive,
    out: Path,
    *,
    storage: str = "mcap",
    **layout: Any,
) -> Path:
    """Write a drive as a rosbag2 folder (version 9, uncompressed, each type's definition embedded),
    with rosbags' writer.

    Args:
        drive: the drive (see the module docstring).
        out: the bag folder to create; it must not exist.
        storage: `mcap` or `sqlite3`.
        layout: the topics and the timing, as `ros_messages` takes them.

    Returns:
        The bag folder.

    Raises:
        ValueError: an option out of its choices, a frame whose arrays have the wrong shape or size, or
            sensors that give no rig (SensorSetupError).
        rosbags.rosbag2.WriterError: `out` exists already.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    check_choice("storage", storage, ("mcap", "sqlite3"))
    typestore = ros_typestore()
    messages = ros_messages(drive, typestore, **layout)
    connections = {}
    with Writer(out, version=9, storage_plugin=StoragePlugin[storage.upper()]) as writer:
        for message in messages:
            if message.topic not in connections:
                connections[message.topic] = writer.add_connection(
                    message.topic, message.type_name, typestore=typestore
                )
            data = typestore.serialize_cdr(message.body, message.type_name)
            writer.write(connections[message.topic], message.time_ns, data)
    return out


def write_ros2_mcap(
    drive: Drive,
    out_file: Path,
    *,
    compression: str = "zstd",
    **layout: Any,
) -> Path:
    """Write a drive as one bare MCAP file (profile `ros2`, CDR messages, `ros2msg` schemas, chunks
    compressed), with mcap-ros2-support's writer: the storage file of a bag, without its metadata.yaml.

    Args:
        drive: the drive (see the module docstring).
        out_file: the .mcap file to create; it must not exist.
        compression: the chunks' compression, `zstd`, `lz4` or `none`.
        layout: the topics and the timing, as `ros_messages` takes them.

    Returns:
        The file.

    Raises:
        ValueError: an option out of its choices, a frame whose arrays have the wrong shape or size, or
            sensors that give no rig (SensorSetupError).
        FileExistsError: `out_file` exists already.
    """
    from mcap.writer import CompressionType
    from mcap_ros2.writer import Writer

    check_choice("compression", compression, COMPRESSIONS)
    typestore = ros_typestore()
    messages = ros_messages(drive, typestore, **layout)
    schemas = {}
    with open(out_file, "xb") as stream, Writer(stream, compression=CompressionType[compression.upper()]) as writer:
        for message in messages:
            if message.type_name not in schemas:
                definition, _ = typestore.generate_msgdef(message.type_name, ros_version=2)
                schemas[message.type_name] = writer.register_msgdef(message.type_name, definition)
            writer.write_message(
                message.topic,
                schemas[message.type_name],
                _plain(message.body),
                log_time=message.time_ns,
                publish_time=message.time_ns,
            )
    return out_file


def _plain(value: Any) -> Any:
    """A rosbags message as the nested dicts mcap-ros2-support encodes: uint8 arrays as bytes, other
    arrays as lists."""
    if is_dataclass(value):
        return {f.name: _plain(getattr(value, f.name)) for f in fields(value) if not f.name.startswith("__")}
    if isinstance(value, np.ndarray):
        return value.tobytes() if value.dtype == np.uint8 else value.tolist()
    if isinstance(value, list):
        return [_plain(item) for item in value]
    return value


# Foxglove ------------------------------------------------------------------------------------------
