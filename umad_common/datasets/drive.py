"""A drive: the frames one recording holds, in time order, whatever format it is stored in.

Two formats implement `Drive`, each in its own module:

- `anovox`: an AnoVox scenario folder (`Scenario_*`, either layout), as CARLA and
  `umad generate synthetic` write it;
- `recording`: a ROS 2 bag (a rosbag2 folder with MCAP or SQLite3 storage, or a bare `.mcap` or
  `.db3`) or an MCAP with Foxglove schemas (protobuf or JSON), as a test vehicle, the CARLA ROS
  bridge or a dataset converter writes it (`umad_common.datasets.recording`).

`find_drives(root)` lists the drives under a folder from names and listings only; `open_drive`
opens one. A folder with `normal/` and `anomalous/` parts is a benchmark: training reads the first
(`normal_root`), evaluation the second. Every verb that takes `--data` and the replayer read drives
through these two functions only.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# What the world model sees; never labels. `label_free` drives open only these.
SENSOR_MODALITIES = ("rgb", "lidar", "action", "route")
LABEL_MODALITIES = ("anomaly", "semantic", "instance", "depth")
MCAP_MAGIC = b"\x89MCAP0\r\n"
UMAD_LOG_PROFILE = "umad"  # the MCAP profile of UMAD's own recorded logs (not drives)
BAG_METADATA = "metadata.yaml"
STORAGE_SUFFIXES = (".mcap", ".db3")


class DatasetError(ValueError):
    """A drive folder or file that cannot be read; the message names the path and what was expected."""


@dataclass(frozen=True)
class EgoState:
    """The ego's speed (m/s) and controls (CARLA ranges: throttle, brake in [0, 1], steer in [-1, 1],
    positive to the right)."""

    speed_mps: float = 0.0
    throttle: float = 0.0
    brake: float = 0.0
    steer: float = 0.0

    def as_array(self) -> np.ndarray:
        return np.array([self.speed_mps, self.throttle, self.brake, self.steer], np.float32)


@dataclass
class DriveFrame:
    """One camera frame of a drive and what the other sensors and labels hold at its time."""

    frame_id: int
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray | None  # (H, W) float32 metres
    semantic: np.ndarray | None  # (H, W) uint8 CARLA tags
    instance: np.ndarray | None  # (H, W) int32 object ids, 0 = none
    anomaly: np.ndarray  # (H, W) uint8 0 / 1, 255 = not labelled
    lidar: np.ndarray | None  # (N, 4) float32 (x forward, y left, z up, intensity) in the lidar's frame
    ego: EgoState
    route: np.ndarray | None  # (192, 192) uint8


class Drive(ABC):
    """One drive; frames load lazily by index.

    Attributes:
        path: the drive's folder or file.
        name: the drive's name: its runs in a graph and its rows in `per_scenario.md` are named so.
        every: one frame in `every` of the recording is kept.
        sensors: the camera and lidar mounts (`umad_common.datasets.sensor_rig`), None when the drive
            does not say (the graph's calibration options then apply).
        modalities: what its frames carry, of SENSOR_MODALITIES and LABEL_MODALITIES (`action`: the ego).
    """

    path: Path
    name: str
    every: int
    sensors: dict | None
    modalities: frozenset[str]

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def __getitem__(self, index: int) -> DriveFrame: ...

    @abstractmethod
    def stamp_ns(self, index: int) -> int:
        """The time of frame `index`: the recording's own clock where it has one."""

    def __iter__(self) -> Iterator[DriveFrame]:
        for index in range(len(self)):
            yield self[index]

    def notes(self) -> list[str]:
        """What this drive lacks or how it was read, a line each (for `umad data info` and the run's summary)."""
        return []

    def describe(self) -> str:
        """The drive's format in words (`AnoVox folder, generator layout`, `ROS 2 bag, MCAP storage`)."""
        return type(self).__name__

    def info(self) -> dict:
        """What `umad data info` prints of this drive."""
        frames = len(self)
        duration = (self.stamp_ns(frames - 1) - self.stamp_ns(0)) / 1e9 if frames > 1 else 0.0
        return {
            "name": self.name,
            "path": str(self.path),
            "format": self.describe(),
            "frames": frames,
            "duration_s": round(duration, 3),
            "rate_hz": round((frames - 1) / duration, 3) if duration > 0 else None,
            "modalities": sorted(self.modalities),
            "notes": self.notes(),
        }

    def check_index(self, index: int) -> int:
        """`index` as a non-negative index, or IndexError naming the drive."""
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame index {index} out of range for {len(self)} frames of {self.name}")
        return index % len(self)


def drive_format(path: Path) -> str | None:
    """`anovox`, `recording` or None (not a drive; UMAD's own logs are not), from names and headers."""
    from umad_common.datasets.anovox import is_scenario_dir

    if path.is_dir():
        if (path / BAG_METADATA).is_file():
            return "recording"
        return "anovox" if is_scenario_dir(path) else None
    if path.suffix == ".db3" and path.is_file():
        return "recording"
    if path.suffix == ".mcap" and path.is_file():
        return None if mcap_profile(path) == UMAD_LOG_PROFILE else "recording"
    return None


def mcap_profile(path: Path) -> str | None:
    """The profile an MCAP file's header names (`ros2`, `umad`, ...), or None if it has no readable header."""
    with open(path, "rb") as f:
        head = f.read(4096)
    if not head.startswith(MCAP_MAGIC) or len(head) < len(MCAP_MAGIC) + 13 or head[8] != 0x01:
        return None
    start = len(MCAP_MAGIC) + 9  # opcode (1) and record length (8)
    size = int.from_bytes(head[start : start + 4], "little")
    return head[start + 4 : start + 4 + size].decode("utf-8", "replace")


def find_drives(root: str | Path) -> list[Path]:
    """Every drive under root (root itself if it is one), sorted by path. A bag folder or a scenario
    folder is one drive and is not searched further; UMAD's own logs are skipped."""
    root = Path(root)
    if not root.exists():
        raise DatasetError(
            f"{root}: no such folder or file; expected drives: AnoVox Scenario_* folders, ROS 2 bags "
            "(a folder with metadata.yaml, or a .mcap / .db3 file) or MCAP files with Foxglove schemas"
        )
    if drive_format(root) is not None:
        return [root]
    found: list[Path] = []
    if root.is_dir():
        for child in sorted(root.iterdir()):
            if child.is_dir() or child.suffix in STORAGE_SUFFIXES:
                found += find_drives(child)
    return found


def drive_name(path: Path) -> str:
    """A drive's name: its folder's name, or a bare recording's file name without suffix."""
    return path.name if path.is_dir() else path.stem


def normal_root(data: str | Path) -> Path:
    """DATA/normal for a benchmark with normal/ and anomalous/ parts, else DATA itself."""
    data = Path(data)
    return data / "normal" if (data / "normal").is_dir() else data


def anomalous_root(data: str | Path) -> Path:
    """DATA/anomalous for a benchmark with normal/ and anomalous/ parts, else DATA itself."""
    data = Path(data)
    return data / "anomalous" if (data / "anomalous").is_dir() else data


def open_drive(
    path: str | Path,
    every: int = 1,
    topics: str | dict[str, str] | None = None,
    keep: tuple[str, ...] | None = None,
    allow_truncated: bool = False,
) -> Drive:
    """The drive at `path`, in whichever format it is.

    Args:
        path: a drive (see `find_drives`).
        every: keep every k-th frame (k >= 1).
        topics: for recordings, the topic of each role (`camera=/a,lidar=/b`, see
            `umad_common.datasets.topics`); unnamed roles are chosen by type. AnoVox folders ignore it.
        keep: open only these modalities (e.g. SENSOR_MODALITIES: a reader that cannot see labels);
            None: all.
        allow_truncated: read a recording cut off by a crash up to the damage (refused otherwise).

    Raises:
        DatasetError: the path is not a drive, or cannot be read; the message says what was expected.
    """
    path = Path(path)
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    kind = drive_format(path) if path.exists() else None
    if kind == "anovox":
        from umad_common.datasets.anovox import AnoVoxScenario

        return AnoVoxScenario(path, every=every, keep=keep)
    if kind == "recording":
        from umad_common.datasets.recording import RecordingDrive

        return RecordingDrive(path, every=every, topics=topics, keep=keep, allow_truncated=allow_truncated)
    raise DatasetError(
        f"{path}: not a drive; expected an AnoVox Scenario_* folder, a ROS 2 bag (a folder with metadata.yaml, "
        "or a .mcap / .db3 file) or an MCAP file with Foxglove schemas"
    )


def training_drives(
    data: str | Path, topics: str | dict[str, str] | None = None, every: int = 1, keep=SENSOR_MODALITIES
) -> list[Drive]:
    """The normal drives a training verb reads (DATA/normal when it exists, else DATA), label-free.

    Raises:
        DatasetError: DATA holds no drive, or one cannot be read.
    """
    root = normal_root(data)
    paths = find_drives(root)
    if not paths:
        raise DatasetError(f"{root}: no drives found; expected normal drives (AnoVox folders or recordings)")
    return [label_free_drive(path, every, topics, keep) for path in paths]


def label_free_drive(
    path: str | Path, every: int = 1, topics: str | dict[str, str] | None = None, keep=SENSOR_MODALITIES
) -> Drive:
    """A drive whose reader cannot open labels: what trains or calibrates a model on normal drives
    reads them through this (modalities outside `keep` come back as None, or zeros for `anomaly`)."""
    if any(modality in LABEL_MODALITIES for modality in keep):
        raise ValueError(f"keep {keep} holds a label modality; a label-free drive keeps only {SENSOR_MODALITIES}")
    return open_drive(path, every=every, topics=topics, keep=tuple(keep))
