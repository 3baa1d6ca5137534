"""ROS 2 bags and Foxglove MCAP recordings as drives (one `Drive` format).

The messages are read through `umad_common.datasets.recording_stores`, with the formats' own
libraries (no message parser of our own).

One drive per recording; the camera is the clock. Its messages, in log-time order (the time the
recorder received them: what `ros2 bag play` and Foxglove order by), are the frames; each frame takes
the lidar, labels, odometry and control messages nearest its time within half a camera period
(frames without one are counted, `unmatched`). A frame's stamp is its camera message's log time, so a
run over a bag is recorded on the bag's own timeline. Roles and topics: `umad_common.datasets.topics`;
message fields: `umad_common.datasets.recording_messages`; the ego's actions without a control topic
and the rig from `/tf_static` and the camera info: docs/design.md ("Own drives").
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from umad_common.datasets.drive import (
    DatasetError,
    Drive,
    DriveFrame,
    EgoState,
    drive_name,
)
from umad_common.datasets.recording_messages import (
    Intrinsics,
    Transform,
    camera_rgb,
    cloud_points,
    control_of,
    frame_id_of,
    intrinsics_of,
    label_mask,
    odometry_of,
    transforms_of,
)
from umad_common.datasets.recording_stores import open_store
from umad_common.datasets.topics import ROLE_TYPES, Choice, choose_topics, parse_topics

FRAME_ROLES = ("lidar", "labels")  # read with each frame
LABEL_IGNORE = 255  # a frame of a labelled drive whose labels message is missing: not scored
MIN_STEER_SPEED = 1.0  # m/s: below it the yaw rate is read as at this speed (no steer blow-up at a standstill)
# A camera in an optical frame (z forward, x right, y down) -> the same camera in body axes (x forward,
# y left, z up): the columns are the body axes written in optical coordinates.
BODY_TO_OPTICAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


class RecordingDrive(Drive):
    """A ROS 2 bag or Foxglove MCAP recording as a drive (see the module docstring).

    Args:
        path: the rosbag2 folder, or the .mcap / .db3 file.
        every: keep every k-th camera frame.
        topics: role -> topic (`camera=/a,lidar=/b` or a dict); unnamed roles are chosen by type.
        keep: read only these modalities (`rgb`, `lidar`, `action`, `anomaly`); None: all.
        allow_truncated: read a recording cut off by a crash up to the damage.

    Attributes:
        roles: role -> the topics it reads and why they were chosen.
        unmatched: role -> frames that found no message of it within half a camera period.
    """

    def __init__(
        self,
        path: str | Path,
        every: int = 1,
        topics: str | dict[str, str] | None = None,
        keep: tuple[str, ...] | None = None,
        allow_truncated: bool = False,
    ):
        self.path = Path(path)
        self.name = drive_name(self.path)
        self.every = every
        self.store = open_store(self.path)
        where = str(self.path)
        kept = {"camera"} | {
            role
            for role, modality in (("lidar", "lidar"), ("labels", "anomaly"), ("odometry", "action"))
            if keep is None or modality in keep
        }
        kept |= {"control"} if "odometry" in kept else set()
        kept |= {"camera_info", "tf"} if "lidar" in kept else set()
        roles = choose_topics(self.store.topics, parse_topics(topics), where, kept)
        self.roles: dict[str, list[Choice]] = {role: c for role, c in roles.items() if role in kept}
        for role, choices in self.roles.items():
            for choice in choices:
                why = self.store.undecodable(choice.topic)
                if why:
                    raise DatasetError(
                        f"{where}: topic {choice.topic} ({choice.type}) for the {role} cannot be decoded: {why}"
                    )
        self.topic = {role: choices[0].topic for role, choices in self.roles.items()}
        self.type = {role: choices[0].type for role, choices in self.roles.items()}
        timed = [self.topic[r] for r in ("camera", *FRAME_ROLES) if r in self.topic]
        times = self.store.times(timed)
        if self.store.truncated and not allow_truncated:
            readable = len(times[self.topic["camera"]])
            raise DatasetError(
                f"{where}: {self.store.truncated}; {readable} camera frames are readable before the damage: pass "
                "--allow-truncated to use them (replayer: allow_truncated: true), or expected a complete recording"
            )
        camera = np.unique(times[self.topic["camera"]])
        if len(camera) == 0:
            raise DatasetError(f"{where}: the camera topic {self.topic['camera']} holds no messages; expected frames")
        self.period_ns = int(np.median(np.diff(camera))) if len(camera) > 1 else 0
        self.tolerance_ns = self.period_ns // 2 if self.period_ns else np.iinfo(np.int64).max // 4
        self.frame_times = camera[::every]
        self.recorded_frames = len(camera)
        self.unmatched: dict[str, int] = {}
        self.matched: dict[str, np.ndarray] = {}  # role -> per frame, the matched message's time (-1: none)
        for role in FRAME_ROLES:
            if role in self.topic:
                self.matched[role] = self.nearest(np.unique(times[self.topic[role]]), role)
        self.ego = self.ego_series()
        self.sensors, self.rig_note = self.read_rig()
        self.modalities = frozenset(
            {"rgb"}
            | ({"lidar"} if "lidar" in self.topic else set())
            | ({"action"} if {"odometry", "control"} & set(self.topic) else set())
            | ({"anomaly"} if "labels" in self.topic else set())
        )

    def nearest(self, stamps: np.ndarray, role: str) -> np.ndarray:
        """For each frame, the time of the message in `stamps` nearest it within the tolerance, else -1
        (counted in `unmatched[role]`)."""
        if len(stamps) == 0:
            self.unmatched[role] = len(self.frame_times)
            return np.full(len(self.frame_times), -1, np.int64)
        right = np.clip(np.searchsorted(stamps, self.frame_times), 1, max(len(stamps) - 1, 1))
        left = right - 1
        candidates = np.stack([stamps[left], stamps[np.minimum(right, len(stamps) - 1)]])
        gaps = np.abs(candidates - self.frame_times)
        best = candidates[np.argmin(gaps, axis=0), np.arange(len(self.frame_times))]
        best = np.where(gaps.min(axis=0) <= self.tolerance_ns, best, -1)
        missing = int((best < 0).sum())
        if missing:
            self.unmatched[role] = missing
        return best

    def series(self, role: str) -> tuple[np.ndarray, list]:
        """All messages of a small role's topic, decoded: (times, messages)."""
        topic = self.topic[role]
        stamps, messages = [], []
        for _, stamp, message in self.store.messages([topic], 0, np.iinfo(np.int64).max):
            stamps.append(stamp)
            messages.append(message)
        return np.asarray(stamps, np.int64), messages

    def ego_series(self) -> list[EgoState]:
        """Each frame's EgoState from the odometry and the control (docs/design.md, "Own drives")."""
        from umad_common.datasets.synthetic.scenario import MAX_ACCEL, MAX_DECEL, MAX_STEER_RAD, WHEELBASE_M

        frames = len(self.frame_times)
        speed = np.zeros(frames)
        throttle, brake, steer = np.zeros(frames), np.zeros(frames), np.zeros(frames)
        has_speed = np.zeros(frames, bool)
        if "odometry" in self.topic:
            stamps, messages = self.series("odometry")
            samples = [odometry_of(m, self.type["odometry"]) for m in messages]
            order = np.argsort(stamps, kind="stable")
            stamps, samples = stamps[order], [samples[i] for i in order]
            seconds = (stamps - stamps[0]) / 1e9 if len(stamps) else stamps
            if samples and samples[0].pose is not None:  # poses: speed and yaw rate over the step that ends there
                poses = np.array([s.pose for s in samples])
                v, yaw_rate = np.zeros(len(poses)), np.zeros(len(poses))
                if len(poses) > 1 and np.all(np.diff(seconds) > 0):
                    dt = np.diff(seconds)
                    v[1:] = np.hypot(*np.diff(poses[:, :2], axis=0).T) / dt
                    yaw_rate[1:] = np.diff(np.unwrap(poses[:, 2])) / dt
                    v[0], yaw_rate[0] = v[1], yaw_rate[1]
            else:
                v = np.array([s.speed for s in samples])
                yaw_rate = np.array([s.yaw_rate for s in samples])
            unique = len(seconds) > 1 and np.all(np.diff(seconds) > 0)
            accel = np.gradient(v, seconds) if unique else np.zeros(len(v))
            at = self.nearest(stamps, "odometry")
            index = np.searchsorted(stamps, at)
            ok = at >= 0
            speed[ok], has_speed[ok] = v[index[ok]], True
            a, rate = accel[index[ok]], yaw_rate[index[ok]]
            throttle[ok] = np.clip(a / MAX_ACCEL, 0, 1)
            brake[ok] = np.clip(-a / MAX_DECEL, 0, 1)
            curvature = rate / np.maximum(speed[ok], MIN_STEER_SPEED)
            steer[ok] = np.clip(-np.arctan(WHEELBASE_M * curvature) / MAX_STEER_RAD, -1, 1)
        if "control" in self.topic:
            stamps, messages = self.series("control")
            order = np.argsort(stamps, kind="stable")
            stamps = stamps[order]
            commands = [control_of(messages[i], self.type["control"]) for i in order]
            at = self.nearest(stamps, "control")
            index = np.searchsorted(stamps, at)
            for frame in np.flatnonzero(at >= 0):
                command = commands[index[frame]]
                throttle[frame], brake[frame], steer[frame] = command.throttle, command.brake, command.steer
                if not has_speed[frame] and command.speed is not None:
                    speed[frame] = command.speed
        return [
            EgoState(float(v), float(t), float(b), float(s))
            for v, t, b, s in zip(speed, throttle, brake, steer, strict=True)
        ]

    def read_rig(self) -> tuple[dict | None, str]:
        """The camera and lidar mounts (`sensors`, see `umad_common.datasets.sensor_rig`) from the
        transforms and the camera info, and a line saying where they came from or what is missing."""
        missing = [role for role in ("lidar", "camera_info", "tf") if role not in self.topic]
        if missing:
            return None, f"no {' or '.join(missing)} topic: the graph's calibration options apply"
        _, infos = self.series("camera_info")
        if not infos:
            return None, f"the camera info topic {self.topic['camera_info']} is empty: the calibration options apply"
        info = intrinsics_of(infos[0], self.type["camera_info"], f"{self.path}: {self.topic['camera_info']}")
        transforms: dict[str, Transform] = {}
        for choice in self.roles["tf"]:
            for _, _, message in self.store.messages([choice.topic], 0, np.iinfo(np.int64).max):
                for transform in transforms_of(message, choice.type):
                    transforms.setdefault(transform.child, transform)
        camera_frame = frame_id_of(infos[0]).lstrip("/")
        lidar_frame = self.lidar_frame()
        rig = rig_from_transforms(transforms, camera_frame, lidar_frame, info)
        if rig is None:
            return None, (
                f"the transforms do not join the camera's frame {camera_frame!r} and the lidar's {lidar_frame!r}: "
                "the graph's calibration options apply"
            )
        return rig, f"camera {camera_frame!r} and lidar {lidar_frame!r} placed in {rig['frames']['vehicle']!r}"

    def lidar_frame(self) -> str:
        for stamp in self.matched["lidar"]:
            if stamp >= 0:
                for _, _, message in self.store.messages([self.topic["lidar"]], int(stamp), int(stamp) + 1):
                    return frame_id_of(message).lstrip("/")
        return ""

    def __len__(self) -> int:
        return len(self.frame_times)

    def __repr__(self) -> str:
        return f"RecordingDrive({str(self.path)!r}, frames={len(self)}, every={self.every})"

    def stamp_ns(self, index: int) -> int:
        return int(self.frame_times[self.check_index(index)])

    def __getitem__(self, index: int) -> DriveFrame:
        index = self.check_index(index)
        wanted = {"camera": int(self.frame_times[index])}
        wanted |= {role: int(m[index]) for role, m in self.matched.items() if m[index] >= 0}
        topics = {self.topic[role]: role for role in wanted}
        got: dict[str, Any] = {}
        for topic, stamp, message in self.store.messages(list(topics), min(wanted.values()), max(wanted.values()) + 1):
            role = topics[topic]
            if stamp == wanted[role] and role not in got:
                got[role] = message
        where = f"{self.path}: {self.topic['camera']} at {wanted['camera']} ns"
        if "camera" not in got:
            raise DatasetError(f"{where}: the camera message cannot be read again; expected the recording unchanged")
        rgb = camera_rgb(got["camera"], self.type["camera"], where)
        anomaly = np.zeros(rgb.shape[:2], np.uint8)
        if "labels" in self.topic:
            anomaly[:] = LABEL_IGNORE
            if "labels" in got:
                labels = label_mask(got["labels"], self.type["labels"], f"{self.path}: {self.topic['labels']}")
                if labels.shape != rgb.shape[:2]:
                    raise DatasetError(
                        f"{self.path}: {self.topic['labels']}: labels of {labels.shape[1]}x{labels.shape[0]}; "
                        f"expected {rgb.shape[1]}x{rgb.shape[0]} like the camera"
                    )
                anomaly = labels
        lidar = None
        if "lidar" in self.topic:
            lidar = np.zeros((0, 4), np.float32)
            if "lidar" in got:
                lidar = cloud_points(got["lidar"], self.type["lidar"], f"{self.path}: {self.topic['lidar']}")
        frame_id = index * self.every
        return DriveFrame(frame_id, rgb, None, None, None, anomaly, lidar, self.ego[index], None)

    def notes(self) -> list[str]:
        notes = []
        if self.store.truncated:
            notes.append(f"truncated: {self.store.truncated}; read up to the damage")
        for role, count in self.unmatched.items():
            notes.append(f"{count} of {len(self)} frames have no {role} message within half a camera period")
        if "lidar" not in self.topic:
            notes.append("no lidar: diff_lidar and geometry masks cannot run")
        if "labels" not in self.topic:
            notes.append("no labels: `umad eval` refuses it, `umad launch` runs")
        if not {"odometry", "control"} & set(self.topic):
            notes.append("no odometry or control: the world model's speed and actions are zero")
        elif "control" not in self.topic:
            notes.append("no control: the actions are derived from the odometry (docs/design.md)")
        notes.append(f"rig: {self.rig_note}")
        return notes

    def describe(self) -> str:
        return self.store.kind

    def info(self) -> dict:
        """What `umad data info` prints of this drive: also each role's topic and why it was chosen."""
        return super().info() | {
            "roles": {
                role: [
                    {"topic": c.topic, "type": c.type, "why": c.why, "messages": self.store.counts.get(c.topic, 0)}
                    for c in choices
                ]
                for role in ROLE_TYPES
                if (choices := self.roles.get(role))
            },
        }


def rig_from_transforms(
    transforms: dict[str, Transform], camera_frame: str, lidar_frame: str, info: Intrinsics
) -> dict | None:
    """The `sensors` of a rig whose camera and lidar frames the transforms join (both placed in their
    nearest common ancestor frame, the vehicle's), else None. A camera in an optical frame (z forward)
    is turned to body axes first."""
    chains = {}
    for name, frame in (("camera", camera_frame), ("lidar", lidar_frame)):
        chain, seen = [frame], {frame}
        while chain[-1] in transforms and transforms[chain[-1]].parent not in seen:
            chain.append(transforms[chain[-1]].parent)
            seen.add(chain[-1])
        chains[name] = chain
    common = [frame for frame in chains["camera"] if frame in chains["lidar"]]
    if not camera_frame or not lidar_frame or not common:
        return None
    vehicle = common[0]

    def placed(frame: str) -> tuple[np.ndarray, np.ndarray]:
        rotation, translation = np.eye(3), np.zeros(3)
        while frame != vehicle:
            t = transforms[frame]
            rotation, translation = t.rotation @ rotation, t.rotation @ translation + t.translation
            frame = t.parent
        return rotation, translation

    camera_rotation, camera_position = placed(camera_frame)
    if camera_rotation[0, 2] > camera_rotation[0, 0]:  # its z axis points further forward than its x: optical
        camera_rotation = camera_rotation @ BODY_TO_OPTICAL
    lidar_rotation, lidar_position = placed(lidar_frame)
    fov = float(np.degrees(2 * np.arctan(info.width / 2 / info.fx)))

    def carla(position: np.ndarray) -> list[float]:
        return [float(position[0]), float(-position[1]), float(position[2])]

    return {
        "camera": {
            "width": info.width,
            "height": info.height,
            "fov": fov,
            "location": carla(camera_position),
            "rotation": [0.0, 0.0, 0.0],
            "focal": [info.fx, info.fy],
            "centre": [info.cx, info.cy],
            "axes": camera_rotation.tolist(),
        },
        "lidar": {"location": carla(lidar_position), "rotation": [0.0, 0.0, 0.0], "axes": lidar_rotation.tolist()},
        "frames": {"camera": camera_frame, "lidar": lidar_frame, "vehicle": vehicle},
    }
