"""The recording writers, read back with the libraries that own the formats (rosbags' AnyReader,
mcap with mcap-ros2-support's and mcap-protobuf-support's decoders, JSON): every topic, type, stamp
and value the package docstring of `umad_common.datasets.writers` promises, on a hand-made
drive whose answers are known, and one generated AnoVox drive written bit-exactly."""

from __future__ import annotations

import base64
import json
import math
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import cv2
import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory
from rosbags.highlevel import AnyReader

from umad_common.datasets.synthetic.scenario import MAX_ACCEL, MAX_DECEL, MAX_STEER_RAD, WHEELBASE_M
from umad_common.datasets.writers import CLOUD_PADDING_BYTE, PERIOD_NS, START_NS
from umad_common.datasets.writers.foxglove import foxglove_json_schema, write_foxglove_mcap
from umad_common.datasets.writers.ros2 import write_ros2_mcap, write_rosbag2

WIDTH, HEIGHT, FOV = 16, 12, 90.0
FOCAL = WIDTH / 2 / math.tan(math.radians(FOV) / 2)
CAMERA_AT, LIDAR_AT = (1.5, 0.25, 1.6), (0.2, -0.3, 1.9)  # CARLA axes: y right
SENSORS = {
    "camera": {"width": WIDTH, "height": HEIGHT, "fov": FOV, "location": list(CAMERA_AT), "rotation": [0, 0, 0]},
    "lidar": {"location": list(LIDAR_AT), "rotation": [0, 0, 0]},
}
SPEEDS, STEERS = (4.0, 5.0, 6.0, 7.0), (0.0, 0.2, -0.3, 0.1)
NO_CLOUD_FRAME = 2  # this frame's lidar is None
ROS_TOPICS = {
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
    "/camera/image_raw": "sensor_msgs/msg/Image",
    "/labels": "sensor_msgs/msg/Image",
    "/lidar/points": "sensor_msgs/msg/PointCloud2",
    "/odom": "nav_msgs/msg/Odometry",
    "/control": "carla_msgs/msg/CarlaEgoVehicleControl",
}
FOXGLOVE_TOPICS = {
    "/tf": "foxglove.FrameTransforms",
    "/camera/calibration": "foxglove.CameraCalibration",
    "/camera/image": "foxglove.RawImage",
    "/labels": "foxglove.RawImage",
    "/lidar/points": "foxglove.PointCloud",
    "/ego/pose": "foxglove.PoseInFrame",
}


@dataclass
class HandMadeFrame:
    frame_id: int
    rgb: np.ndarray
    lidar: np.ndarray | None
    ego: SimpleNamespace
    anomaly: np.ndarray


@dataclass
class HandMadeDrive:
    name: str
    sensors: dict | None
    frames: list[HandMadeFrame]

    def __iter__(self):
        return iter(self.frames)


@pytest.fixture(scope="module")
def drive() -> HandMadeDrive:
    rng = np.random.default_rng(3)
    frames = []
    for index, (speed, steer) in enumerate(zip(SPEEDS, STEERS, strict=True)):
        anomaly = np.zeros((HEIGHT, WIDTH), np.uint8)
        anomaly[index : index + 3, 2:7] = 1
        cloud = None if index == NO_CLOUD_FRAME else rng.normal(0, 10, (50 + index, 4)).astype(np.float32)
        ego = SimpleNamespace(speed_mps=speed, throttle=0.1 * index, brake=0.05 * index, steer=steer)
        frames.append(
            HandMadeFrame(100 + index, rng.integers(0, 256, (HEIGHT, WIDTH, 3), np.uint8), cloud, ego, anomaly)
        )
    return HandMadeDrive("Scenario_handmade", SENSORS, frames)


def frame_time(index: int, offset_ns: int = 0) -> int:
    return START_NS + index * PERIOD_NS + offset_ns


def stamp_ns(header) -> int:
    return header.stamp.sec * 10**9 + header.stamp.nanosec


def read_bag(path: Path) -> tuple[dict, dict[str, list[tuple[int, object]]]]:
    """(topic -> connection, topic -> [(log time, message)]) with rosbags' AnyReader."""
    with AnyReader([path]) as reader:
        connections = {c.topic: c for c in reader.connections}
        messages: dict[str, list[tuple[int, object]]] = {topic: [] for topic in connections}
        for connection, time_ns, raw in reader.messages():
            messages[connection.topic].append((time_ns, reader.deserialize(raw, connection.msgtype)))
    return connections, messages


def byte_array(data) -> np.ndarray:
    """A uint8[] field as rosbags (a numpy array) or mcap-ros2-support (bytes) decodes it."""
    return np.frombuffer(data, np.uint8) if isinstance(data, bytes) else np.asarray(data, np.uint8)


def check_ros_messages(messages: dict[str, list[tuple[int, object]]], drive: HandMadeDrive) -> None:
    """Every value the ROS 2 writers promise, with no offsets and the default options."""
    ((tf_time, tf),) = messages["/tf_static"]
    assert tf_time == START_NS
    transforms = {t.child_frame_id: t for t in tf.transforms}
    assert {t.header.frame_id for t in tf.transforms} == {"base_link"}
    camera, lidar = transforms["camera_optical"].transform, transforms["lidar"].transform
    x, y, z = CAMERA_AT
    assert (camera.translation.x, camera.translation.y, camera.translation.z) == pytest.approx((x, -y, z))
    assert (camera.rotation.x, camera.rotation.y, camera.rotation.z, camera.rotation.w) == (-0.5, 0.5, -0.5, 0.5)
    x, y, z = LIDAR_AT
    assert (lidar.translation.x, lidar.translation.y, lidar.translation.z) == pytest.approx((x, -y, z))
    assert (lidar.rotation.x, lidar.rotation.y, lidar.rotation.z, lidar.rotation.w) == (0, 0, 0, 1)

    for topic in ("/camera/camera_info", "/camera/image_raw", "/labels", "/odom", "/control"):
        assert [time for time, _ in messages[topic]] == [frame_time(i) for i in range(len(drive.frames))], topic
        assert all(stamp_ns(message.header) == time for time, message in messages[topic]), topic
    for index, frame in enumerate(drive.frames):
        _, info = messages["/camera/camera_info"][index]
        assert (info.header.frame_id, info.width, info.height, info.distortion_model) == (
            "camera_optical",
            WIDTH,
            HEIGHT,
            "plumb_bob",
        )
        assert list(info.d) == [0.0] * 5
        assert list(info.k) == pytest.approx([FOCAL, 0, WIDTH / 2, 0, FOCAL, HEIGHT / 2, 0, 0, 1])
        assert list(info.r) == [1, 0, 0, 0, 1, 0, 0, 0, 1]
        assert list(info.p) == pytest.approx([FOCAL, 0, WIDTH / 2, 0, 0, FOCAL, HEIGHT / 2, 0, 0, 0, 1, 0])
        _, image = messages["/camera/image_raw"][index]
        assert (image.header.frame_id, image.encoding, image.is_bigendian, image.step) == (
            "camera_optical",
            "rgb8",
            0,
            3 * WIDTH,
        )
        assert np.array_equal(byte_array(image.data).reshape(HEIGHT, WIDTH, 3), frame.rgb)
        _, labels = messages["/labels"][index]
        assert (labels.encoding, labels.step, labels.header.frame_id) == ("mono8", WIDTH, "camera_optical")
        assert np.array_equal(byte_array(labels.data).reshape(HEIGHT, WIDTH), frame.anomaly * 255)
        _, odometry = messages["/odom"][index]
        assert (odometry.header.frame_id, odometry.child_frame_id) == ("odom", "base_link")
        assert odometry.twist.twist.linear.x == frame.ego.speed_mps
        _, control = messages["/control"][index]
        assert (control.throttle, control.steer, control.brake) == pytest.approx(
            (frame.ego.throttle, frame.ego.steer, frame.ego.brake)
        )
    clouds = messages["/lidar/points"]
    with_cloud = [(i, f) for i, f in enumerate(drive.frames) if f.lidar is not None]
    assert [time for time, _ in clouds] == [frame_time(i) for i, _ in with_cloud]
    for (_, cloud), (_, frame) in zip(clouds, with_cloud, strict=True):
        assert (cloud.header.frame_id, cloud.height, cloud.width, cloud.point_step) == (
            "lidar",
            1,
            len(frame.lidar),
            16,
        )
        assert [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields] == [
            ("x", 0, 7, 1),
            ("y", 4, 7, 1),
            ("z", 8, 7, 1),
            ("intensity", 12, 7, 1),
        ]
        assert (cloud.row_step, cloud.is_bigendian, cloud.is_dense) == (16 * len(frame.lidar), False, True)
        assert np.array_equal(byte_array(cloud.data).view("<f4").reshape(-1, 4), frame.lidar)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_rosbag2_holds_every_topic_with_its_stamps_and_values(drive, tmp_path, storage):
    bag = write_rosbag2(drive, tmp_path / "bag", storage=storage)
    assert (bag / "metadata.yaml").is_file()
    assert (bag / f"bag.{'mcap' if storage == 'mcap' else 'db3'}").is_file()
    connections, messages = read_bag(bag)
    assert {topic: c.msgtype for topic, c in connections.items()} == ROS_TOPICS
    # The control type is not one ROS ships: the bag embeds its definition, as every other type's.
    assert "float32 throttle" in connections["/control"].msgdef.data
    assert all(c.msgdef.data for c in connections.values())
    check_ros_messages(messages, drive)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_ros2_mcap_is_chunk_compressed_and_readable_by_both_libraries(drive, tmp_path, compression):
    path = write_ros2_mcap(drive, tmp_path / "drive.mcap", compression=compression)
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[Ros2DecoderFactory()])
        summary = reader.get_summary()
        assert reader.get_header().profile == "ros2"
        assert {c.compression for c in summary.chunk_indexes} == {"" if compression == "none" else compression}
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()} == ROS_TOPICS
        decoded = {topic: [] for topic in ROS_TOPICS}
        for _, channel, message, ros_message in reader.iter_decoded_messages(log_time_order=False):
            assert message.log_time == message.publish_time
            decoded[channel.topic].append((message.log_time, ros_message))
    check_ros_messages(decoded, drive)
    _, messages = read_bag(path)  # rosbags reads the bare file and its compressed chunks too
    check_ros_messages(messages, drive)


def test_offsets_move_each_role_and_messages_are_written_in_log_time_order(drive, tmp_path):
    offsets = {"lidar": -3_000_000, "odometry": 5_000_000, "control": 1_000_000}
    path = write_ros2_mcap(drive, tmp_path / "drive.mcap", offsets_ns=offsets)
    with open(path, "rb") as stream:
        written = [
            (channel.topic, message.log_time)
            for _, channel, message in make_reader(stream).iter_messages(log_time_order=False)
        ]
    assert written[0] == ("/tf_static", START_NS - 3_000_000)  # first, before the earliest lidar cloud
    assert [time for _, time in written] == sorted(time for _, time in written)
    _, messages = read_bag(path)
    for topic, role in (("/lidar/points", "lidar"), ("/odom", "odometry"), ("/control", "control")):
        for time, message in messages[topic]:
            assert stamp_ns(message.header) == time
            assert (time - START_NS - offsets[role]) % PERIOD_NS == 0, topic
    assert [t for t, _ in messages["/camera/image_raw"]] == [frame_time(i) for i in range(len(drive.frames))]


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "jpeg", "png"])
def test_image_encodings(drive, tmp_path, encoding):
    bag = write_rosbag2(drive, tmp_path / "bag", image_encoding=encoding, labels=False, lidar=False, max_frames=2)
    connections, messages = read_bag(bag)
    compressed = encoding in ("jpeg", "png")
    topic = "/camera/image_raw/compressed" if compressed else "/camera/image_raw"
    assert set(connections) == {"/tf_static", "/camera/camera_info", topic, "/odom", "/control"}
    assert len(messages[topic]) == 2
    for (_, image), frame in zip(messages[topic], drive.frames, strict=False):
        rgb = frame.rgb
        if compressed:
            assert image.format == encoding
            # The same bytes as OpenCV's own encoding of the BGR image (JPEG: quality 95); PNG is lossless.
            params = [cv2.IMWRITE_JPEG_QUALITY, 95] if encoding == "jpeg" else []
            _, expected = cv2.imencode(f".{'jpg' if encoding == 'jpeg' else 'png'}", rgb[..., ::-1], params)
            assert np.array_equal(byte_array(image.data), expected.reshape(-1))
            decoded = cv2.imdecode(byte_array(image.data), cv2.IMREAD_COLOR)[..., ::-1]
            assert decoded.shape == rgb.shape and (encoding == "jpeg" or np.array_equal(decoded, rgb))
            continue
        channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}[encoding]
        assert (image.encoding, image.step) == (encoding, WIDTH * channels)
        pixels = byte_array(image.data).reshape(HEIGHT, WIDTH, channels)
        expected = {
            "rgb8": rgb,
            "bgr8": rgb[..., ::-1],
            "rgba8": np.dstack([rgb, np.full((HEIGHT, WIDTH), 255)]),
            "bgra8": np.dstack([rgb[..., ::-1], np.full((HEIGHT, WIDTH), 255)]),
            "mono8": cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[..., None],
        }[encoding]
        assert np.array_equal(pixels, expected)


def test_ackermann_control_padded_clouds_and_left_out_topics(drive, tmp_path):
    bag = write_rosbag2(drive, tmp_path / "bag", control="ackermann", cloud_padding=4, odometry=False, rig=False)
    connections, messages = read_bag(bag)
    assert set(connections) == {"/camera/image_raw", "/labels", "/lidar/points", "/control"}
    assert connections["/control"].msgtype == "ackermann_msgs/msg/AckermannDriveStamped"
    assert "float32 steering_angle" in connections["/control"].msgdef.data
    for (_, command), frame in zip(messages["/control"], drive.frames, strict=True):
        ego = frame.ego
        assert command.drive.speed == pytest.approx(ego.speed_mps)
        assert command.drive.steering_angle == pytest.approx(-ego.steer * MAX_STEER_RAD, abs=1e-6)
        assert command.drive.acceleration == pytest.approx(ego.throttle * MAX_ACCEL - ego.brake * MAX_DECEL, abs=1e-6)
    frames_with_cloud = [f for f in drive.frames if f.lidar is not None]
    for (_, cloud), frame in zip(messages["/lidar/points"], frames_with_cloud, strict=True):
        assert (cloud.point_step, cloud.row_step) == (20, 20 * len(frame.lidar))
        rows = byte_array(cloud.data).reshape(-1, 20)
        assert np.array_equal(rows[:, :16].copy().view("<f4"), frame.lidar)
        assert (rows[:, 16:] == CLOUD_PADDING_BYTE).all()


def read_foxglove(path: Path) -> tuple[dict[str, str], dict[str, list[tuple[int, object]]], set[str]]:
    """(topic -> schema name, topic -> [(log time, message)], chunk compressions); protobuf messages
    decoded by mcap-protobuf-support, JSON ones as dicts, validated against their schemas."""
    with open(path, "rb") as stream:
        reader, protobuf = make_reader(stream), ProtobufDecoderFactory()
        summary = reader.get_summary()
        types = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        messages: dict[str, list[tuple[int, object]]] = {topic: [] for topic in types}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert message.log_time == message.publish_time
            if channel.message_encoding == "json":
                assert schema.encoding == "jsonschema"
                body = json.loads(message.data)
                jsonschema.validate(body, json.loads(schema.data))
            else:
                assert (channel.message_encoding, schema.encoding) == ("protobuf", "protobuf")
                body = protobuf.decoder_for("protobuf", schema)(message.data)
            messages[channel.topic].append((message.log_time, body))
    return types, messages, {c.compression for c in summary.chunk_indexes}


def field(message, name):
    """A field of a protobuf message or of a JSON dict."""
    return message[name] if isinstance(message, dict) else getattr(message, name)


def foxglove_ns(message) -> int:
    stamp = field(message, "timestamp")
    if isinstance(stamp, dict):
        return stamp["sec"] * 10**9 + stamp["nsec"]
    return stamp.seconds * 10**9 + stamp.nanos


def foxglove_bytes(message, name: str = "data") -> bytes:
    data = field(message, name)
    return base64.b64decode(data) if isinstance(data, str) else data


@pytest.mark.parametrize(("encoding", "compression"), [("protobuf", "zstd"), ("json", "lz4")])
def test_foxglove_mcap_holds_every_topic_with_its_stamps_and_values(drive, tmp_path, encoding, compression):
    path = write_foxglove_mcap(drive, tmp_path / "drive.mcap", encoding=encoding, compression=compression)
    types, messages, compressions = read_foxglove(path)
    assert types == FOXGLOVE_TOPICS
    assert compressions == {compression}
    ((tf_time, tf),) = messages["/tf"]
    assert tf_time == START_NS
    transforms = {field(t, "child_frame_id"): t for t in field(tf, "transforms")}
    translation = field(transforms["lidar"], "translation")
    x, y, z = LIDAR_AT
    assert [field(translation, k) for k in "xyz"] == pytest.approx([x, -y, z])
    rotation = field(transforms["camera_optical"], "rotation")
    assert [field(rotation, k) for k in "xyzw"] == [-0.5, 0.5, -0.5, 0.5]
    for topic in ("/camera/calibration", "/camera/image", "/labels", "/ego/pose"):
        times = [time for time, _ in messages[topic]]
        assert times == [frame_time(i) for i in range(len(drive.frames))], topic
        assert all(foxglove_ns(message) == time for time, message in messages[topic]), topic
    previous = None
    for index, frame in enumerate(drive.frames):
        _, calibration = messages["/camera/calibration"][index]
        assert list(field(calibration, "K")) == pytest.approx([FOCAL, 0, WIDTH / 2, 0, FOCAL, HEIGHT / 2, 0, 0, 1])
        assert len(field(calibration, "P")) == 12 and list(field(calibration, "D")) == [0.0] * 5
        _, image = messages["/camera/image"][index]
        assert (field(image, "encoding"), field(image, "step"), field(image, "frame_id")) == (
            "rgb8",
            3 * WIDTH,
            "camera_optical",
        )
        assert np.array_equal(np.frombuffer(foxglove_bytes(image), np.uint8).reshape(HEIGHT, WIDTH, 3), frame.rgb)
        _, labels = messages["/labels"][index]
        assert np.array_equal(
            np.frombuffer(foxglove_bytes(labels), np.uint8).reshape(HEIGHT, WIDTH), frame.anomaly * 255
        )
        # The reader derives the speed from the pose: one period's displacement is the frame's speed.
        _, pose = messages["/ego/pose"][index]
        position = field(field(pose, "pose"), "position")
        here = np.array([field(position, "x"), field(position, "y")])
        if previous is not None:
            assert np.linalg.norm(here - previous) / (PERIOD_NS / 1e9) == pytest.approx(frame.ego.speed_mps)
        previous = here
    # The heading turns by the steering's yaw rate (positive steer: right, so clockwise).
    orientation = field(field(messages["/ego/pose"][-1][1], "pose"), "orientation")
    yaw = 2 * math.atan2(field(orientation, "z"), field(orientation, "w"))
    rates = [v * math.tan(-s * MAX_STEER_RAD) / WHEELBASE_M for v, s in zip(SPEEDS[1:], STEERS[1:], strict=True)]
    assert yaw == pytest.approx(sum(rates) * PERIOD_NS / 1e9)
    with_cloud = [f for f in drive.frames if f.lidar is not None]
    assert len(messages["/lidar/points"]) == len(with_cloud)
    for (_, cloud), frame in zip(messages["/lidar/points"], with_cloud, strict=True):
        assert (field(cloud, "frame_id"), field(cloud, "point_stride")) == ("lidar", 16)
        assert [(field(f, "name"), field(f, "offset"), field(f, "type")) for f in field(cloud, "fields")] == [
            ("x", 0, 7),
            ("y", 4, 7),
            ("z", 8, 7),
            ("intensity", 12, 7),
        ]
        assert np.array_equal(np.frombuffer(foxglove_bytes(cloud), "<f4").reshape(-1, 4), frame.lidar)


@pytest.mark.parametrize(("image", "encoding"), [("jpeg", "protobuf"), ("png", "json")])
def test_foxglove_compressed_images(drive, tmp_path, image, encoding):
    path = write_foxglove_mcap(
        drive, tmp_path / "drive.mcap", encoding=encoding, image=image, labels=False, lidar=False, rig=False
    )
    types, messages, _ = read_foxglove(path)
    assert types == {"/camera/image": "foxglove.CompressedImage", "/ego/pose": "foxglove.PoseInFrame"}
    for (_, message), frame in zip(messages["/camera/image"], drive.frames, strict=True):
        assert field(message, "format") == image
        decoded = cv2.imdecode(np.frombuffer(foxglove_bytes(message), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
        assert decoded.shape == frame.rgb.shape
        if image == "png":
            assert np.array_equal(decoded, frame.rgb)


def test_foxglove_json_schemas_are_the_published_ones_where_vendored():
    assert foxglove_json_schema("foxglove.PointCloud")["title"] == "foxglove.PointCloud"
    transforms = foxglove_json_schema("foxglove.FrameTransforms")
    assert transforms["properties"]["transforms"]["items"]["title"] == "foxglove.FrameTransform"
    assert foxglove_json_schema("foxglove.RawImage") == {"title": "foxglove.RawImage", "type": "object"}


def test_bad_options_and_frames_are_refused(drive, tmp_path):
    with pytest.raises(ValueError, match="storage = 'rosbag'"):
        write_rosbag2(drive, tmp_path / "a", storage="rosbag")
    with pytest.raises(ValueError, match="image_encoding = 'yuv'"):
        write_ros2_mcap(drive, tmp_path / "a.mcap", image_encoding="yuv")
    with pytest.raises(ValueError, match=r"offsets_ns names \['labels'\]"):
        write_foxglove_mcap(drive, tmp_path / "b.mcap", offsets_ns={"labels": 1})
    small = HandMadeDrive("Scenario_small", None, drive.frames)  # AnoVox's rig: 768x512, not 16x12
    with pytest.raises(
        ValueError, match="Scenario_small frame 100: image is 16x12; expected the rig's camera, 768x512"
    ):
        write_foxglove_mcap(small, tmp_path / "c.mcap")
    (tmp_path / "exists.mcap").write_bytes(b"")
    with pytest.raises(FileExistsError):
        write_ros2_mcap(drive, tmp_path / "exists.mcap")


def test_a_generated_anovox_drive_is_written_bit_exactly(tmp_path):
    from umad_common.datasets.anovox import AnoVoxScenario
    from umad_common.datasets.synthetic.generator import generate_benchmark

    (root,) = generate_benchmark(tmp_path / "data", normal=0, anomalous=1, frames=3, seed=7, size=(96, 64))
    scenario = AnoVoxScenario(root)
    _, messages = read_bag(write_rosbag2(scenario, tmp_path / "bag", image_encoding="bgra8"))
    frames = list(scenario)
    assert len(messages["/camera/image_raw"]) == len(messages["/lidar/points"]) == len(frames) == 3
    for (_, image), (_, cloud), (_, labels), frame in zip(
        messages["/camera/image_raw"], messages["/lidar/points"], messages["/labels"], frames, strict=True
    ):
        assert np.array_equal(byte_array(image.data).reshape(64, 96, 4)[..., 2::-1], frame.rgb)
        assert np.array_equal(byte_array(cloud.data).view("<f4").reshape(-1, 4), frame.lidar)
        assert np.array_equal(byte_array(labels.data).reshape(64, 96), frame.anomaly * 255)
    assert any(frame.anomaly.any() for frame in frames)
