"""Writers of drive recordings: a drive as a ROS 2 bag, as one bare ROS 2 MCAP file, or as an MCAP with
Foxglove schemas, laid out as a vehicle's recorder would write it and as the recording reader
(`umad_common.datasets.recording`) expects. Tests and `umad bench data` write their recordings here.

A drive is any object with `name`, `sensors` (the camera and lidar mounts, see
`umad_common.datasets.sensor_rig`; None: AnoVox's rig) and frames in iteration order with `rgb`,
`lidar` ((N, 4) float32 x forward, y left, z up, intensity, in the lidar's frame, as REP 103; or
None), `ego` (speed_mps, throttle, brake, steer: CARLA's ranges and sign, steer positive to the right)
and `anomaly` ((H, W) uint8 0 / 1), such as `umad_common.datasets.drive.Drive`.

Time: frame i (in iteration order) is stamped t_i = start_ns + i * period_ns, and each of its messages
has log time = publish time = header stamp = t_i + the offset of its role (ROLES; `offsets_ns`, 0 by
default, lets a recording put the lidar or the odometry a few ms off the camera; the labels and the
camera's calibration go with the camera). The rig's transforms are written once, at t_0 (earlier by
the most negative offset, so they come first). Messages are written in log-time order.

Frames: `base_link` is the vehicle (REP 103 axes); `camera_optical` the camera (x right, y down,
z forward); `lidar` the lidar (REP 103 axes); `odom` the drive's start.

ROS 2 topics: `/camera/image_raw` (sensor_msgs/Image) or `/camera/image_raw/compressed`
(sensor_msgs/CompressedImage), `/camera/camera_info`, `/tf_static`, `/lidar/points` (PointCloud2),
`/odom` (nav_msgs/Odometry: the speed as twist.linear.x, the yaw rate as twist.angular.z), `/control` (carla_msgs/CarlaEgoVehicleControl
or ackermann_msgs/AckermannDriveStamped), `/labels` (mono8 Image, anomaly * 255). Foxglove topics:
`/camera/image` (RawImage or CompressedImage), `/camera/calibration`, `/tf` (FrameTransforms),
`/lidar/points` (PointCloud), `/ego/pose` (PoseInFrame, dead-reckoned: see `DeadReckoning`), `/labels`.
"""

from __future__ import annotations

import base64
import heapq
import itertools
import json
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from umad_common.datasets.recording import ros_typestore
from umad_common.datasets.sensor_rig import SensorRig
from umad_common.datasets.synthetic.scenario import MAX_ACCEL, MAX_DECEL, MAX_STEER_RAD, WHEELBASE_M

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

    from umad_common.datasets.drive import Drive

START_NS = 1_700_000_000 * 10**9
PERIOD_NS = 100_000_000  # 10 Hz, as AnoVox
ROLES = ("camera", "lidar", "odometry", "control")  # what `offsets_ns` may move
BASE_FRAME, CAMERA_FRAME, LIDAR_FRAME, ODOM_FRAME = "base_link", "camera_optical", "lidar", "odom"
OPTICAL_ROTATION = (-0.5, 0.5, -0.5, 0.5)  # quaternion (x, y, z, w): base_link axes -> camera_optical axes
IDENTITY_ROTATION = (0.0, 0.0, 0.0, 1.0)
IMAGE_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
COMPRESSED_FORMATS = ("jpeg", "png")
JPEG_QUALITY = 95
CLOUD_FIELDS = ("x", "y", "z", "intensity")  # each FLOAT32 at 4 * index
FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32 and foxglove.NumericType FLOAT32 alike
CLOUD_PADDING_BYTE = 0xAB  # fills `cloud_padding` bytes after each point: a reader ignoring point_step reads junk
COMPRESSIONS = ("zstd", "lz4", "none")
ROS_CONTROL_TYPES = {
    "carla": "carla_msgs/msg/CarlaEgoVehicleControl",
    "ackermann": "ackermann_msgs/msg/AckermannDriveStamped",
}
FOXGLOVE_JSON_SCHEMAS = Path(__file__).parents[1] / "viz" / "foxglove_schemas"  # @foxglove/schemas, vendored


@dataclass(frozen=True)
class Stamped:
    """One message to write: its log time, topic, type and body (a rosbags message, or a Foxglove dict)."""

    time_ns: int
    topic: str
    type_name: str
    body: Any


@dataclass(frozen=True)
class Rig:
    """The camera's pinhole intrinsics and both sensors' mounts on `base_link` (REP 103 axes, metres)."""

    width: int
    height: int
    focal: float  # px, fx = fy
    camera_translation: tuple[float, float, float]
    lidar_translation: tuple[float, float, float]

    @classmethod
    def of(cls, drive: Drive) -> Rig:
        """The drive's rig (`sensors`, CARLA axes), AnoVox's where it names none.

        Raises:
            SensorSetupError: the sensors lack the camera or the lidar, or rotate either.
        """
        rig = SensorRig.anovox() if drive.sensors is None else SensorRig.from_sensors(drive.sensors, drive.name)
        focal = rig.width / 2 / math.tan(math.radians(rig.fov) / 2)
        return cls(rig.width, rig.height, focal, _ros_axes(rig.camera_location), _ros_axes(rig.lidar_location))

    @property
    def k(self) -> list[float]:
        return [self.focal, 0.0, self.width / 2, 0.0, self.focal, self.height / 2, 0.0, 0.0, 1.0]

    @property
    def p(self) -> list[float]:
        return [self.focal, 0.0, self.width / 2, 0.0, 0.0, self.focal, self.height / 2, 0.0, 0.0, 0.0, 1.0, 0.0]

    def transforms(self) -> list[tuple[str, tuple[float, float, float], tuple[float, float, float, float]]]:
        """(child frame, translation, rotation (x, y, z, w)) of each sensor under `base_link`."""
        return [
            (CAMERA_FRAME, self.camera_translation, OPTICAL_ROTATION),
            (LIDAR_FRAME, self.lidar_translation, IDENTITY_ROTATION),
        ]


def _ros_axes(carla: tuple[float, float, float]) -> tuple[float, float, float]:
    """A CARLA location (y right) in REP 103 axes (y left)."""
    x, y, z = carla
    return (float(x), 0.0 - float(y), float(z))  # 0.0 - y: no -0.0 for a centred mount


class DeadReckoning:
    """The ego's planar pose in `odom`, from its speed and steering (a kinematic bicycle with the
    synthetic world's wheelbase and steering range): frame 0 at the origin facing x; frame i turns by
    its yaw rate over one period and moves speed_i * period along the mean of the two headings, so
    |position_i - position_(i-1)| / period = speed_i exactly."""

    def __init__(self, period_ns: int):
        self.period_s = period_ns / 1e9
        self.x = self.y = self.yaw = 0.0
        self.started = False

    def advance(self, speed_mps: float, steer: float) -> tuple[float, float, float]:
        """The pose (x, y, yaw: rad, counter-clockwise) at the next frame."""
        if self.started:
            yaw_rate = speed_mps * math.tan(-steer * MAX_STEER_RAD) / WHEELBASE_M
            heading = self.yaw + yaw_rate * self.period_s / 2
            self.x += speed_mps * self.period_s * math.cos(heading)
            self.y += speed_mps * self.period_s * math.sin(heading)
            self.yaw += yaw_rate * self.period_s
        self.started = True
        return self.x, self.y, self.yaw


def _check_choice(name: str, value: object, allowed: Iterable[object]) -> None:
    if value not in tuple(allowed):
        raise ValueError(f"{name} = {value!r}; expected one of {tuple(allowed)}")


def _stamped_frames(
    drive: Drive, start_ns: int, period_ns: int, offsets: dict[str, int], max_frames: int | None
) -> Iterator[tuple[Any, dict[str, int]]]:
    """Each frame (at most max_frames) with the time of each role's messages, its shapes checked."""
    for index, frame in enumerate(itertools.islice(drive, max_frames)):
        _check_frame(frame, drive.name)
        time_ns = start_ns + index * period_ns
        yield frame, {role: time_ns + offset for role, offset in offsets.items()}


def _check_frame(frame: Any, where: str) -> None:
    rgb, lidar = frame.rgb, frame.lidar
    what = f"{where} frame {frame.frame_id}"
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"{what}: rgb is {rgb.dtype} of shape {rgb.shape}; expected (H, W, 3) uint8")
    if lidar is not None and (lidar.ndim != 2 or lidar.shape[1] != 4):
        raise ValueError(f"{what}: lidar of shape {lidar.shape}; expected (N, 4) x, y, z, intensity")


def _label_mask(frame: Any, where: str) -> np.ndarray:
    """The frame's anomaly truth as a mono8 image (H, W, 1): 255 anomaly, 0 not."""
    anomaly = np.asarray(frame.anomaly)
    if anomaly.shape != frame.rgb.shape[:2] or (anomaly > 1).any():
        raise ValueError(
            f"{where} frame {frame.frame_id}: anomaly of shape {anomaly.shape} (largest value {anomaly.max()}); "
            f"expected {frame.rgb.shape[:2]} holding 0 and 1 only (labels=False writes a drive without labels)"
        )
    return (anomaly.astype(np.uint8) * 255)[..., None]


def _check_size(rig: Rig, frame: Any, where: str) -> None:
    height, width = frame.rgb.shape[:2]
    if (width, height) != (rig.width, rig.height):
        raise ValueError(
            f"{where} frame {frame.frame_id}: image is {width}x{height}; expected the rig's camera, "
            f"{rig.width}x{rig.height} (the drive's `sensors`, or AnoVox's rig where it has none)"
        )


def _in_log_time_order(batches: Iterable[tuple[int, list[Stamped]]]) -> Iterator[Stamped]:
    """The messages of every batch in log-time order (equal times in the order given). Each batch is
    (bound_ns, messages): no message of a later batch comes before bound_ns."""
    pending: list[tuple[int, int, Stamped]] = []
    order = itertools.count()
    for bound_ns, batch in batches:
        for message in batch:
            heapq.heappush(pending, (message.time_ns, next(order), message))
        while pending and pending[0][0] < bound_ns:
            yield heapq.heappop(pending)[2]
    while pending:
        yield heapq.heappop(pending)[2]


def _scheduled(
    drive: Drive,
    source: RosMessages | FoxgloveMessages,
    start_ns: int,
    period_ns: int,
    offsets_ns: dict[str, int] | None,
    max_frames: int | None,
) -> Iterator[Stamped]:
    """The source's static messages, then every frame's, in log-time order; the timing checked first.

    Raises:
        ValueError: a period that is not positive, max_frames below 1, an offset of no role of ROLES.
    """
    if period_ns <= 0:
        raise ValueError(f"period_ns = {period_ns}; expected a positive period")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames = {max_frames}; expected at least 1 frame, or None for all")
    if unknown := set(offsets_ns or {}) - set(ROLES):
        raise ValueError(f"offsets_ns names {sorted(unknown)}; expected roles of {ROLES}")
    offsets = {role: int((offsets_ns or {}).get(role, 0)) for role in ROLES}
    earliest = min(0, *offsets.values())  # the earliest message of frame i is at t_i + earliest
    first = [(start_ns + earliest, source.static(start_ns + earliest))]
    frames = (
        (times["camera"] - offsets["camera"] + period_ns + earliest, source.frame(frame, times))
        for frame, times in _stamped_frames(drive, start_ns, period_ns, offsets, max_frames)
    )
    return _in_log_time_order(itertools.chain(first, frames))


def _compressed(rgb: np.ndarray, image_format: str) -> bytes:
    """An RGB image as JPEG (quality JPEG_QUALITY) or PNG bytes."""
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if image_format == "jpeg" else []
    ok, encoded = cv2.imencode(".jpg" if image_format == "jpeg" else ".png", rgb[..., ::-1], params)
    if not ok:
        raise ValueError(f"cannot encode an image of shape {rgb.shape} as {image_format}")
    return encoded.tobytes()


def _pixels(rgb: np.ndarray, encoding: str) -> np.ndarray:
    """An RGB image in a ROS image encoding, (H, W, channels) uint8."""
    if encoding == "mono8":
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[..., None]
    colour = rgb[..., ::-1] if encoding.startswith("bgr") else rgb
    if IMAGE_CHANNELS[encoding] == 4:
        return np.dstack([colour, np.full(rgb.shape[:2], 255, np.uint8)])
    return np.ascontiguousarray(colour)


def _cloud_bytes(points: np.ndarray, padding: int) -> np.ndarray:
    """(N, 4) points as little-endian float32 x, y, z, intensity, each point followed by `padding`
    bytes of CLOUD_PADDING_BYTE: (N * (16 + padding),) uint8."""
    packed = np.full((len(points), 16 + padding), CLOUD_PADDING_BYTE, np.uint8)
    packed[:, :16] = np.ascontiguousarray(points, "<f4").view(np.uint8).reshape(-1, 16)
    return packed.reshape(-1)


# ROS 2 ---------------------------------------------------------------------------------------------


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
        _check_choice("image_encoding", image_encoding, (*IMAGE_CHANNELS, *COMPRESSED_FORMATS))
        _check_choice("control", control, (*ROS_CONTROL_TYPES, None))
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
        _check_size(self.camera, frame, self.drive.name)
        t, at = self.types, times["camera"]
        messages = []
        if self.rig:
            messages.append(Stamped(at, "/camera/camera_info", "sensor_msgs/msg/CameraInfo", self._camera_info(at)))
        messages.append(self._image(frame.rgb, at))
        if self.labels:
            mask = self._raw_image(_label_mask(frame, self.drive.name), "mono8", at)
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
            data = np.frombuffer(_compressed(rgb, self.image_encoding), np.uint8)
            message = self.types["sensor_msgs/msg/CompressedImage"](
                header=self._header(time_ns, CAMERA_FRAME), format=self.image_encoding, data=data
            )
            return Stamped(time_ns, "/camera/image_raw/compressed", "sensor_msgs/msg/CompressedImage", message)
        message = self._raw_image(_pixels(rgb, self.image_encoding), self.image_encoding, time_ns)
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
            data=_cloud_bytes(points, self.cloud_padding),
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
        ValueError: an option out of its choices, or timing that cannot be (see `_scheduled`).
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
    return _scheduled(drive, source, start_ns, period_ns, offsets_ns, max_frames)


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

    _check_choice("storage", storage, ("mcap", "sqlite3"))
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

    _check_choice("compression", compression, COMPRESSIONS)
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


class FoxgloveMessages:
    """A drive's messages of Foxglove schemas as dicts in Foxglove's field names: times in ns under
    `timestamp`, byte fields as bytes (see `_json_body` and `_protobuf_body` for the encodings)."""

    def __init__(self, drive: Drive, *, image: str, labels: bool, lidar: bool, rig: bool, period_ns: int):
        _check_choice("image", image, ("raw", *COMPRESSED_FORMATS))
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
        _check_size(self.camera, frame, self.drive.name)
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
                "data": _compressed(frame.rgb, self.image),
                "format": self.image,
            }
            messages.append(Stamped(at, "/camera/image", "foxglove.CompressedImage", compressed))
        if self.labels:
            mask = _raw_image(_label_mask(frame, self.drive.name), "mono8", at)
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
                "data": _cloud_bytes(frame.lidar, 0).tobytes(),
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

    _check_choice("encoding", encoding, ("protobuf", "json"))
    _check_choice("compression", compression, COMPRESSIONS)
    source = FoxgloveMessages(drive, image=image, labels=labels, lidar=lidar, rig=rig, period_ns=period_ns)
    messages = _scheduled(drive, source, start_ns, period_ns, offsets_ns, max_frames)
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
    writer.start(profile="", library="umad recording_writers")
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
