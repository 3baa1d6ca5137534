"""The drive formats, and the functions every verb and the replayer read drives through.

`FORMATS` lists the formats in the order a path is tried: each says whether a path is one of its
drives (from names and headers only, no payload read) and opens it with its reader. The readers
(`anovox`, `recording`) implement `umad_common.datasets.drive.Drive`; this module is above them
all: no reader imports it, nor another reader.

`find_drives(root)` lists the drives under a folder; `open_drive` opens one. A folder with `normal/`
and `anomalous/` parts is a benchmark: training reads the first (`normal_root`, `training_drives`),
evaluation the second (`anomalous_root`). Every verb that takes `--data` and the replayer read drives
through these functions only. A new format implements `Drive` in a module of its own and joins
`FORMATS` here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from umad_common.datasets.anovox import AnoVoxScenario, is_scenario_dir
from umad_common.datasets.drive import LABEL_MODALITIES, SENSOR_MODALITIES, STORAGE_SUFFIXES, DatasetError, Drive
from umad_common.datasets.recording import RecordingDrive
from umad_common.datasets.recording_stores import is_recording

DriveOpener = Callable[..., Drive]  # (path, every, topics, keep, allow_truncated) -> Drive


@dataclass(frozen=True)
class DriveFormat:
    """One way drives are stored.

    Attributes:
        name: the format's name (`drive_format` returns it).
        holds: whether a path is a drive of this format, from names and headers only.
        open: its reader: `(path, every, topics, keep, allow_truncated) -> Drive` (see `open_drive`).
    """

    name: str
    holds: Callable[[Path], bool]
    open: DriveOpener


def _open_recording(path, every, topics, keep, allow_truncated) -> Drive:
    return RecordingDrive(path, every=every, topics=topics, keep=keep, allow_truncated=allow_truncated)


def _open_anovox(path, every, topics, keep, allow_truncated) -> Drive:
    return AnoVoxScenario(path, every=every, keep=keep)  # a folder names no topics and is never cut off


# Tried in order: a folder with metadata.yaml is a bag even where its name says Scenario_*.
FORMATS = (
    DriveFormat("recording", is_recording, _open_recording),
    DriveFormat("anovox", is_scenario_dir, _open_anovox),
)


def drive_format(path: Path) -> str | None:
    """The name of the format `path` is a drive of (`recording`, `anovox`), or None (not a drive;
    UMAD's own logs are not), from names and headers."""
    return next((found.name for found in FORMATS if found.holds(path)), None)


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
    found = next((found for found in FORMATS if found.holds(path)), None) if path.exists() else None
    if found is None:
        raise DatasetError(
            f"{path}: not a drive; expected an AnoVox Scenario_* folder, a ROS 2 bag (a folder with metadata.yaml, "
            "or a .mcap / .db3 file) or an MCAP file with Foxglove schemas"
        )
    return found.open(path, every, topics, keep, allow_truncated)


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
