"""A drive: the frames one recording holds, in time order, whatever format it is stored in.

What every drive format shares, and nothing that knows the formats: `Drive` (the interface each
reader implements), `DriveFrame`, `EgoState`, `DatasetError`, the modalities and the names and
headers that tell a drive's storage. Two formats implement `Drive`, each in its own module, which
imports this one:

- `anovox`: an AnoVox scenario folder (`Scenario_*`, either layout), as CARLA and
  `umad generate synthetic` write it;
- `recording`: a ROS 2 bag (a rosbag2 folder with MCAP or SQLite3 storage, or a bare `.mcap` or
  `.db3`) or an MCAP with Foxglove schemas (protobuf or JSON), as a test vehicle, the CARLA ROS
  bridge or a dataset converter writes it (`umad_common.datasets.recording`).

Which format a path is, and the functions every verb reads drives through (`find_drives`,
`open_drive`, `training_drives`, ...), are in `umad_common.datasets.formats`, above the readers.
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


def mcap_profile(path: Path) -> str | None:
    """The profile an MCAP file's header names (`ros2`, `umad`, ...), or None if it has no readable header."""
    with open(path, "rb") as f:
        head = f.read(4096)
    if not head.startswith(MCAP_MAGIC) or len(head) < len(MCAP_MAGIC) + 13 or head[8] != 0x01:
        return None
    start = len(MCAP_MAGIC) + 9  # opcode (1) and record length (8)
    size = int.from_bytes(head[start : start + 4], "little")
    return head[start + 4 : start + 4 + size].decode("utf-8", "replace")


def drive_name(path: Path) -> str:
    """A drive's name: its folder's name, or a bare recording's file name without suffix."""
    return path.name if path.is_dir() else path.stem
