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

import heapq
import itertools
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import cv2
import numpy as np

from umad_common.datasets.sensor_rig import SensorRig
from umad_common.datasets.synthetic.scenario import MAX_STEER_RAD, WHEELBASE_M

if TYPE_CHECKING:
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


def check_choice(name: str, value: object, allowed: Iterable[object]) -> None:
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


def label_mask(frame: Any, where: str) -> np.ndarray:
    """The frame's anomaly truth as a mono8 image (H, W, 1): 255 anomaly, 0 not."""
    anomaly = np.asarray(frame.anomaly)
    if anomaly.shape != frame.rgb.shape[:2] or (anomaly > 1).any():
        raise ValueError(
            f"{where} frame {frame.frame_id}: anomaly of shape {anomaly.shape} (largest value {anomaly.max()}); "
            f"expected {frame.rgb.shape[:2]} holding 0 and 1 only (labels=False writes a drive without labels)"
        )
    return (anomaly.astype(np.uint8) * 255)[..., None]


def check_size(rig: Rig, frame: Any, where: str) -> None:
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


class MessageSource(Protocol):
    """What a format's message builder gives `scheduled`: the messages written once, and one frame's."""

    def static(self, time_ns: int) -> list[Stamped]: ...

    def frame(self, frame: Any, times: dict[str, int]) -> list[Stamped]: ...


def scheduled(
    drive: Drive,
    source: MessageSource,
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


def compressed_image(rgb: np.ndarray, image_format: str) -> bytes:
    """An RGB image as JPEG (quality JPEG_QUALITY) or PNG bytes."""
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if image_format == "jpeg" else []
    ok, encoded = cv2.imencode(".jpg" if image_format == "jpeg" else ".png", rgb[..., ::-1], params)
    if not ok:
        raise ValueError(f"cannot encode an image of shape {rgb.shape} as {image_format}")
    return encoded.tobytes()


def image_pixels(rgb: np.ndarray, encoding: str) -> np.ndarray:
    """An RGB image in a ROS image encoding, (H, W, channels) uint8."""
    if encoding == "mono8":
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[..., None]
    colour = rgb[..., ::-1] if encoding.startswith("bgr") else rgb
    if IMAGE_CHANNELS[encoding] == 4:
        return np.dstack([colour, np.full(rgb.shape[:2], 255, np.uint8)])
    return np.ascontiguousarray(colour)


def cloud_bytes(points: np.ndarray, padding: int) -> np.ndarray:
    """(N, 4) points as little-endian float32 x, y, z, intensity, each point followed by `padding`
    bytes of CLOUD_PADDING_BYTE: (N * (16 + padding),) uint8."""
    packed = np.full((len(points), 16 + padding), CLOUD_PADDING_BYTE, np.uint8)
    packed[:, :16] = np.ascontiguousarray(points, "<f4").view(np.uint8).reshape(-1, 16)
    return packed.reshape(-1)


# ROS 2 ---------------------------------------------------------------------------------------------
