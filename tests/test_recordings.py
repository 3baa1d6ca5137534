"""Own drives: ROS 2 bags (rosbag2 MCAP and SQLite3, bare MCAP) and Foxglove MCAPs, written from the
synthetic world and read back through the one drive reader; every verb on them; each bad input."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import free_port, run_umad
from umad_common.datasets.drive import DatasetError, EgoState
from umad_common.datasets.formats import find_drives, open_drive
from umad_common.datasets.recording import RecordingDrive
from umad_common.datasets.recording_messages import Transform, quaternion_matrix
from umad_common.datasets.sensor_rig import SensorRig
from umad_common.datasets.synthetic.generator import generate_benchmark
from umad_common.datasets.writers.foxglove import write_foxglove_mcap
from umad_common.datasets.writers.ros2 import write_ros2_mcap, write_rosbag2

SIZE = (96, 64)


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth")
    generate_benchmark(out, normal=2, anomalous=1, frames=6, seed=7, size=SIZE)
    return out


@pytest.fixture(scope="module")
def anomalous(synthetic) -> Path:
    return find_drives(synthetic / "anomalous")[0]


WRITERS = {
    "rosbag2-mcap": lambda drive, out: write_rosbag2(drive, out / "bag", storage="mcap"),
    "rosbag2-sqlite3-bgra8-padded": lambda drive, out: write_rosbag2(
        drive, out / "bag", storage="sqlite3", image_encoding="bgra8", cloud_padding=4
    ),
    "ros2-mcap-zstd-bgr8": lambda drive, out: write_ros2_mcap(drive, out / "drive.mcap", image_encoding="bgr8"),
    "ros2-mcap-lz4-rgba8": lambda drive, out: write_ros2_mcap(
        drive, out / "drive.mcap", compression="lz4", image_encoding="rgba8"
    ),
    "foxglove-protobuf": lambda drive, out: write_foxglove_mcap(drive, out / "drive.mcap", encoding="protobuf"),
    "foxglove-json-lz4": lambda drive, out: write_foxglove_mcap(
        drive, out / "drive.mcap", encoding="json", compression="lz4"
    ),
}


@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_a_recording_gives_the_anovox_folders_frames(kind, anomalous, tmp_path):
    source = open_drive(anomalous)
    path = WRITERS[kind](source, tmp_path)
    drive = open_drive(path)
    assert isinstance(drive, RecordingDrive) and len(drive) == len(source) == 6
    assert drive.modalities == {"rgb", "lidar", "action", "anomaly"}
    for index in range(len(source)):
        expected, got = source[index], drive[index]
        assert np.array_equal(got.rgb, expected.rgb), index  # pixel for pixel
        assert got.lidar.dtype == np.float32 and np.array_equal(got.lidar, expected.lidar), index  # point for point
        assert np.array_equal(got.anomaly, expected.anomaly), index
        if not kind.startswith("foxglove"):  # a control topic: the actions as recorded
            assert np.array_equal(got.ego.as_array(), expected.ego.as_array()), index
    assert [drive.stamp_ns(i) for i in range(3)] == [1_700_000_000 * 10**9 + i * 100_000_000 for i in range(3)]
    # the rig from /tf_static and the camera info projects the cloud as AnoVox's sensor_setup.json does
    points = source[2].lidar[:, :3].astype(np.float64)
    ours, theirs = SensorRig.from_sensors(drive.sensors, kind), SensorRig.from_sensors(source.sensors, "anovox")
    for a, b in zip(ours.project(points, (64, 96)), theirs.project(points, (64, 96)), strict=True):
        assert np.array_equal(a, b)


def test_a_folder_of_bags_is_a_set_of_drives_named_by_folder(synthetic, tmp_path):
    names = []
    for path in find_drives(synthetic / "normal"):
        write_rosbag2(open_drive(path), tmp_path / f"drive_{path.name[-4:]}")
        names.append(f"drive_{path.name[-4:]}")
    (tmp_path / "nested").mkdir()
    write_foxglove_mcap(open_drive(find_drives(synthetic / "anomalous")[0]), tmp_path / "nested" / "fox.mcap")
    (tmp_path / "run.mcap").write_bytes((tmp_path / "nested" / "fox.mcap").read_bytes())
    found = find_drives(tmp_path)
    assert [p.name for p in found] == sorted(names) + ["fox.mcap", "run.mcap"]
    assert [open_drive(p).name for p in found] == sorted(names) + ["fox", "run"]
    assert find_drives(tmp_path / sorted(names)[0]) == [tmp_path / sorted(names)[0]]  # a bag is one drive


def test_messages_off_the_camera_are_matched_within_half_a_period_and_counted_otherwise(anomalous, tmp_path):
    source = open_drive(anomalous)
    near = write_rosbag2(source, tmp_path / "near", offsets_ns={"lidar": 30_000_000, "odometry": -40_000_000})
    drive = open_drive(near)
    assert drive.unmatched == {} and np.array_equal(drive[3].lidar, source[3].lidar)
    assert drive[3].ego.speed_mps == pytest.approx(source[3].ego.speed_mps)
    far = write_rosbag2(source, tmp_path / "far", offsets_ns={"lidar": 60_000_000}, control=None)
    drive = open_drive(far)
    assert drive.unmatched == {"lidar": 1}  # each cloud 60 ms after its camera frame: 40 ms before the next one
    assert any("1 of 6 frames have no lidar message within half a camera period" in n for n in drive.notes())
    assert drive[0].lidar.shape == (0, 4) and np.array_equal(drive[3].lidar, source[2].lidar)


def test_without_a_control_topic_the_actions_come_from_the_odometry(anomalous, tmp_path):
    source = open_drive(anomalous)
    frames = [source[i] for i in range(len(source))]
    for path in (
        write_rosbag2(source, tmp_path / "odom_only", control=None),
        write_foxglove_mcap(source, tmp_path / "poses.mcap"),
    ):
        drive = open_drive(path)
        assert any("derived from the odometry" in note for note in drive.notes())
        speeds = np.array([drive[i].ego.speed_mps for i in range(len(drive))])
        truth = np.array([f.ego.speed_mps for f in frames])
        assert np.abs(speeds[1:] - truth[1:]).max() < 1e-6  # poses differenced over the step ending there
        for i in range(len(drive)):
            ego = drive[i].ego
            assert 0 <= ego.throttle <= 1 and 0 <= ego.brake <= 1 and -1 <= ego.steer <= 1
            assert np.sign(ego.steer) == np.sign(frames[i].ego.steer) or abs(frames[i].ego.steer) < 0.01
        braking = [f.ego.brake > f.ego.throttle for f in frames]
        derived = [drive[i].ego.brake > drive[i].ego.throttle for i in range(1, len(drive) - 1)]
        assert derived == braking[1:-1]


def test_a_turned_lidar_and_an_optical_camera_frame_project_with_the_real_rig():
    from umad_common.datasets.recording import rig_from_transforms
    from umad_common.datasets.recording_messages import Intrinsics

    def turn(x, y, z, w):
        return quaternion_matrix(type("Q", (), {"x": x, "y": y, "z": z, "w": w})())

    transforms = {
        "camera_optical": Transform("base_link", "camera_optical", turn(-0.5, 0.5, -0.5, 0.5), np.array([1.0, 0, 1.5])),
        "lidar": Transform("base_link", "lidar", turn(0, 0, np.sqrt(0.5), np.sqrt(0.5)), np.array([0.0, 0, 2.0])),
    }  # the lidar turned 90 degrees left: its x axis is the vehicle's y
    sensors = rig_from_transforms(transforms, "camera_optical", "lidar", Intrinsics(200, 100, 100.0, 100.0, 80.0, 40.0))
    assert sensors["frames"] == {"camera": "camera_optical", "lidar": "lidar", "vehicle": "base_link"}
    assert sensors["camera"]["location"] == [1.0, -0.0, 1.5] and sensors["camera"]["axes"] == np.eye(3).tolist()
    rig = SensorRig.from_sensors(sensors, "test")
    # 11 m ahead of the vehicle at the camera's height: the lidar sees it on its right (-y), 0.5 m down
    rows, cols, depth = rig.project(np.array([[0.0, -11.0, -0.5]]), (100, 200))
    assert (rows[0], cols[0], depth[0]) == (40, 80, pytest.approx(10.0))  # the principal point, 10 m ahead
    rows, cols, _ = rig.project(np.array([[1.0, -11.0, -0.5]]), (50, 100))  # 1 m left; half the image size
    assert (rows[0], cols[0]) == (20, 40 - 5)


def test_umad_data_info_names_each_roles_topic_and_what_is_missing(anomalous, tmp_path):
    source = open_drive(anomalous)
    write_rosbag2(source, tmp_path / "drives" / "full")
    write_ros2_mcap(source, tmp_path / "drives" / "bare.mcap", lidar=False, labels=False, rig=False)
    result = run_umad("data", "info", str(tmp_path / "drives"))
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "drives: 2, 12 frames" in out and "frames 6, 0.50 s at 10.00 Hz" in out
    assert "camera      /camera/image_raw  sensor_msgs/msg/Image  6 messages  (the only camera type)" in out
    assert "labels      /labels  sensor_msgs/msg/Image  6 messages  (its name says labels)" in out
    assert "no lidar: diff_lidar and geometry masks cannot run" in out
    assert "no labels: `umad eval` refuses it, `umad launch` runs" in out
    as_json = json.loads(run_umad("data", "info", str(tmp_path / "drives"), "--json").stdout)
    [full] = [d for d in as_json["drives"] if d["name"] == "full"]
    assert full["roles"]["control"][0]["type"] == "carla_msgs/msg/CarlaEgoVehicleControl"


# ------------------------------------------------------------------------------------------------
# Bad input: one line, exit code 2, before anything starts


def write_custom_bag(path: Path, messages: list[tuple[str, str, object]]) -> Path:
    """A rosbag2 MCAP bag of (topic, type, message) written at 10 Hz, each topic's n-th message at n x 100 ms."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from umad_common.datasets.recording_stores import ros_typestore

    store = ros_typestore()
    counts: dict[str, int] = {}
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}
        for topic, kind, message in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, kind, typestore=store)
            stamp = 10**18 + counts.get(topic, 0) * 100_000_000
            counts[topic] = counts.get(topic, 0) + 1
            writer.write(connections[topic], stamp, store.serialize_cdr(message, kind))
    return path


def ros_image(encoding: str = "rgb8", width: int = 4, height: int = 2):
    from umad_common.datasets.recording_stores import ros_typestore

    t = ros_typestore().types
    channels = {"rgb8": 3, "bgra8": 4, "mono8": 1, "yuv422": 2}[encoding]
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="camera")
    data = np.arange(width * height * channels, dtype=np.uint8)
    return t["sensor_msgs/msg/Image"](
        header=header, height=height, width=width, encoding=encoding, is_bigendian=0, step=width * channels, data=data
    )


def ros_cloud(big_endian: bool):
    from umad_common.datasets.recording_stores import ros_typestore

    t = ros_typestore().types
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="lidar")
    fields = [t["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    data = np.zeros(24, np.uint8)
    return t["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=2, fields=fields, is_bigendian=big_endian, point_step=12, row_step=24,
        data=data, is_dense=True,
    )  # fmt: skip


def refused(*argv: str) -> str:
    result = run_umad(*argv)
    assert result.returncode == 2, (result.returncode, result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


def test_no_camera_topic_is_refused_with_the_topics_listed(tmp_path):
    bag = write_custom_bag(tmp_path / "no_camera", [("/points", "sensor_msgs/msg/PointCloud2", ros_cloud(False))])
    line = refused("data", "info", str(bag))
    assert "no camera topic" in line and "/points (sensor_msgs/msg/PointCloud2)" in line and "--topics camera=" in line


def test_two_camera_candidates_are_listed_with_how_to_pick_one(tmp_path):
    messages = [
        ("/front/image_raw", "sensor_msgs/msg/Image", ros_image()),
        ("/rear/image_raw", "sensor_msgs/msg/Image", ros_image()),
    ]
    bag = write_custom_bag(tmp_path / "two", messages * 2)
    line = refused("eval", "--data", str(bag), "--out", str(tmp_path / "out"))
    assert "2 topics could be the camera" in line
    assert "/front/image_raw (sensor_msgs/msg/Image); /rear/image_raw (sensor_msgs/msg/Image)" in line
    assert "pick one with --topics camera=TOPIC" in line
    assert not (tmp_path / "out").exists()
    drive = open_drive(bag, topics="camera=/rear/image_raw")  # picked: it reads
    assert drive[0].rgb.shape == (2, 4, 3)


def test_a_named_topic_that_is_absent_or_of_the_wrong_type_is_refused(tmp_path):
    messages = [
        ("/cam", "sensor_msgs/msg/Image", ros_image()),
        ("/points", "sensor_msgs/msg/PointCloud2", ros_cloud(False)),
    ]
    bag = write_custom_bag(tmp_path / "bag", messages)
    assert "--topics lidar=/velodyne: no such topic" in refused("data", "info", str(bag), "--topics", "lidar=/velodyne")
    line = refused("data", "info", str(bag), "--topics", "lidar=/cam")
    assert "--topics lidar=/cam has type sensor_msgs/msg/Image; the lidar role takes" in line
    assert "roles ['radar'] are unknown" in refused("data", "info", str(bag), "--topics", "radar=/points")


def test_a_big_endian_cloud_and_an_unknown_image_encoding_name_the_topic(tmp_path):
    messages = [
        ("/cam", "sensor_msgs/msg/Image", ros_image()),
        ("/points", "sensor_msgs/msg/PointCloud2", ros_cloud(True)),
    ]
    drive = open_drive(write_custom_bag(tmp_path / "big", messages))
    with pytest.raises(DatasetError, match=r"/points: a big-endian point cloud; expected a little-endian one"):
        drive[0]
    drive = open_drive(write_custom_bag(tmp_path / "yuv", [("/cam", "sensor_msgs/msg/Image", ros_image("yuv422"))]))
    with pytest.raises(DatasetError, match=r"/cam at .* image encoding 'yuv422' is not supported; expected one of"):
        drive[0]


def test_a_topic_whose_messages_cannot_be_decoded_names_topic_and_type(anomalous, tmp_path):
    from mcap.writer import Writer

    path = tmp_path / "cbor.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="test")
        schema = writer.register_schema("foxglove.RawImage", "jsonschema", b"{}")
        channel = writer.register_channel("/camera/image", "cbor", schema)
        writer.add_message(channel, 10**18, b"\xa0", 10**18)
        writer.finish()
    line = refused("data", "info", str(path))
    assert "topic /camera/image (foxglove.RawImage) for the camera cannot be decoded" in line and "'cbor'" in line


def test_a_recording_cut_off_by_a_crash_is_refused_or_read_up_to_the_damage(anomalous, tmp_path):
    whole = write_ros2_mcap(open_drive(anomalous), tmp_path / "whole.mcap", compression="none")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.6)])
    line = refused("data", "info", str(cut))
    assert "cut off after" in line and "camera frames are readable before the damage" in line
    assert "--allow-truncated" in line
    drive = open_drive(cut, allow_truncated=True)
    assert 0 < len(drive) < 6 and any(note.startswith("truncated:") for note in drive.notes())
    assert np.array_equal(drive[len(drive) - 1].rgb, open_drive(whole)[len(drive) - 1].rgb)


def test_the_recorder_logs_a_recordings_frames_at_the_recordings_own_time():
    from umad_common.dataflow.record.mcap_log import log_time_of

    assert log_time_of(1_700_000_000 * 10**9 + 5) == 1_700_000_000 * 10**9 + 5
    assert log_time_of(300_000_000) > 1_700_000_000 * 10**9  # AnoVox stamps from 0: the time of writing


# ------------------------------------------------------------------------------------------------
# Every verb, as a user runs it


def strip_route(folder: Path) -> None:
    """A recording has no route map: the AnoVox copy it is compared with drops its own."""
    for sub in list(folder.iterdir()):
        if sub.name.startswith("ROUTE_MAP"):
            shutil.rmtree(sub)


def non_gt_rows(table: Path) -> list[list[str]]:
    """table.csv without the GT-mask rows (they need panoptic labels a recording's labels topic lacks)
    and without the rank marks (which rank against those rows)."""
    with open(table) as f:
        rows = list(csv.reader(f))
    header = rows[0]
    keep = [i for i, name in enumerate(header) if not name.endswith("_mark")]
    return [[row[i] for i in keep] for row in rows[1:] if not row[header.index("masks")].startswith("gt")]


@pytest.mark.slow
def test_eval_on_bags_gives_the_table_of_the_same_drives_as_anovox_folders(tmp_path):
    generate_benchmark(tmp_path / "gen", normal=0, anomalous=2, frames=8, seed=5, size=(192, 128))
    for path in find_drives(tmp_path / "gen" / "anomalous"):
        copy = tmp_path / "anovox" / path.name
        shutil.copytree(path, copy)
        strip_route(copy)
        write_rosbag2(open_drive(copy), tmp_path / "bags" / path.name, control="carla")
    hub = f"tcp/127.0.0.1:{free_port()}"
    topics = "camera=/camera/image_raw,lidar=/lidar/points,odometry=/odom,control=/control,labels=/labels"
    for data, out, extra in (("anovox", "e_anovox", []), ("bags", "e_bags", ["--topics", topics])):
        result = run_umad(
            "eval", "--data", str(tmp_path / data), "--out", str(tmp_path / out), "--hub", hub, *extra, timeout=600
        )
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    anovox, bags = non_gt_rows(tmp_path / "e_anovox" / "table.csv"), non_gt_rows(tmp_path / "e_bags" / "table.csv")
    assert len(anovox) > 100 and bags == anovox
    per_scenario = (tmp_path / "e_bags" / "per_scenario.md").read_text()
    assert all(path.name in per_scenario for path in find_drives(tmp_path / "bags"))


@pytest.mark.slow
def test_train_world_model_and_calibrate_run_on_bags(tmp_path):
    generate_benchmark(tmp_path / "gen", normal=2, anomalous=0, frames=12, seed=3, size=SIZE)
    for path in find_drives(tmp_path / "gen" / "normal"):
        write_rosbag2(open_drive(path), tmp_path / "bags" / "normal" / path.name, control=None)
    config = tmp_path / "tiny.json"
    config.write_text(
        json.dumps(
            {
                "config": {
                    "image_height": 32, "image_width": 48, "image_channels": [8, 8], "decoder_channels": [8, 8, 4],
                    "lidar_rows": 16, "lidar_width": 32, "lidar_channels": [8, 8], "lidar_embed": 8,
                    "route_size": 16, "route_channels": [8], "route_embed": 8, "deter_channels": 4,
                    "stoch_channels": 2, "hidden_channels": 8, "transition_kernel": 3,
                },
                "train_config": {"batch_size": 2, "sequence_length": 4},
            }
        )
    )  # fmt: skip
    model = tmp_path / "wm"
    result = run_umad(
        "train", "world-model", str(tmp_path / "bags"), "--out", str(model), "--config", str(config),
        "--epochs", "1", "--threads", "1", "--topics", "camera=/camera/image_raw", timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    record = json.loads(model.with_suffix(".json").read_text())
    assert record["heldout_drives"] == [sorted(p.name for p in find_drives(tmp_path / "gen" / "normal"))[-1]]
    assert "--topics camera=/camera/image_raw" in record["command"]
    result = run_umad(
        "calibrate", str(tmp_path / "bags"), "--world-model", str(model.with_suffix(".safetensors")),
        "--out", str(tmp_path / "calibration.json"), "--frames", "4", "--threads", "1", timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    calibration = json.loads((tmp_path / "calibration.json").read_text())
    assert calibration["info"]["drives"] == record["heldout_drives"] and calibration["info"]["labels_read"] is False


@pytest.mark.slow
def test_launch_runs_on_a_bag_without_labels(anomalous, tmp_path):
    bag = write_rosbag2(open_drive(anomalous), tmp_path / "unlabelled", labels=False)
    hub = f"tcp/127.0.0.1:{free_port()}"
    result = run_umad(
        "launch", "--live", "--set", f"replayer.source={bag}", "--set", "replayer.topics=camera=/camera/image_raw",
        "--set", "replayer.pacing=lossless", "--hub", hub, "--record", str(tmp_path / "run.mcap"), timeout=300,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    from umad_common.dataflow.record.mcap_log import read_log

    stamps = {m.publish_time for m in read_log(tmp_path / "run.mcap") if m.topic.endswith("/replayer/camera")}
    assert stamps == {1_700_000_000 * 10**9 + i * 100_000_000 for i in range(6)}  # the bag's own time
    log_times = {m.log_time for m in read_log(tmp_path / "run.mcap") if m.topic.endswith("/replayer/camera")}
    assert log_times == stamps


def test_ego_state_of_a_frame_without_odometry_is_zero(anomalous, tmp_path):
    drive = open_drive(write_rosbag2(open_drive(anomalous), tmp_path / "bare", odometry=False, control=None))
    assert drive[0].ego == EgoState() and "action" not in drive.modalities
    assert any("no odometry or control" in note for note in drive.notes())


def test_a_reader_of_the_camera_alone_is_not_stopped_by_two_lidars(tmp_path):
    messages = [
        ("/cam", "sensor_msgs/msg/Image", ros_image()),
        ("/front/points", "sensor_msgs/msg/PointCloud2", ros_cloud(False)),
        ("/rear/points", "sensor_msgs/msg/PointCloud2", ros_cloud(False)),
    ]
    bag = write_custom_bag(tmp_path / "two_lidars", messages)
    with pytest.raises(DatasetError, match="2 topics could be the lidar"):
        open_drive(bag)
    drive = open_drive(bag, keep=("rgb",))  # what MNAD and the feature net train on
    assert drive.modalities == {"rgb"} and drive[0].lidar is None
    assert open_drive(bag, topics="lidar=/rear/points")[0].lidar.shape == (2, 4)
