"""`umad bench data`: how fast the drive reader reads a ROS 2 bag against the same drive as AnoVox PNG
folders, side by side in one run.

One generated drive (768 x 512, `frames` frames) is read in two forms: as `umad generate synthetic`
writes it (AnoVox generator layout: PNG camera, depth, semantic and instance images, .npy lidar, .csv
actions; read with `AnoVoxScenario`), and as a rosbag2 written from it (MCAP storage, uncompressed,
the camera raw `bgra8` as a CARLA camera publishes it, with the lidar, odometry, control, labels, tf and
camera info: `umad_common.datasets.writers.ros2.write_rosbag2`; read with `open_drive`). Each
read opens the drive and loads every frame. The two are read alternately, `rounds` times each, so a
machine whose speed drifts moves both sides alike; frames/s is the best round of each side (the read
the machine disturbed least), and `fps_ratio_bag` the bag's over AnoVox's (>= 1: the bag is not
slower). The same is measured label-free (`fps_ratio_bag_label_free`: both drives opened with
SENSOR_MODALITIES, as training reads them: camera, lidar, ego, route, no label image). Both files are
in the page cache, as a drive read a second time is. A last pass checks that both sides give the same
pixels and points.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

SIZE = (768, 512)  # AnoVox's camera
SEED = 1


def bench_data(frames: int = 100, rounds: int = 3) -> dict:
    from umad_common.datasets.anovox import AnoVoxScenario
    from umad_common.datasets.drive import SENSOR_MODALITIES
    from umad_common.datasets.formats import open_drive
    from umad_common.datasets.synthetic.generator import generate_benchmark
    from umad_common.datasets.writers.ros2 import write_rosbag2

    if frames < 1 or rounds < 1:
        raise ValueError(f"frames = {frames}, rounds = {rounds}; expected at least 1 of each")
    with tempfile.TemporaryDirectory(prefix="umad-bench-data-") as work:
        (scenario,) = generate_benchmark(
            Path(work) / "data", normal=1, anomalous=0, frames=frames, seed=SEED, size=SIZE
        )
        bag = write_rosbag2(AnoVoxScenario(scenario), Path(work) / "bag", image_encoding="bgra8")
        sides: dict[str, Callable[[], Iterable]] = {
            "anovox": lambda: AnoVoxScenario(scenario),
            "bag": lambda: open_drive(bag),
            "anovox_label_free": lambda: AnoVoxScenario(scenario, keep=SENSOR_MODALITIES),
            "bag_label_free": lambda: open_drive(bag, keep=SENSOR_MODALITIES),
        }
        seconds: dict[str, list[float]] = {side: [] for side in sides}
        for _ in range(rounds):
            for side, open_side in sides.items():
                seconds[side].append(_read_all(open_side, frames, side))
        same_rgb, same_lidar = _same_frames(sides["anovox"](), sides["bag"]())
        sizes = {"anovox": _folder_bytes(scenario), "bag": _folder_bytes(bag)}
    fps = {side: frames / min(times) for side, times in seconds.items()}
    return {
        "frames": frames,
        "size": f"{SIZE[0]}x{SIZE[1]}",
        "rounds": rounds,
        "statistic": "best round of each side",
        "fps_anovox": fps["anovox"],
        "fps_bag": fps["bag"],
        "fps_ratio_bag": fps["bag"] / fps["anovox"],
        "fps_anovox_label_free": fps["anovox_label_free"],
        "fps_bag_label_free": fps["bag_label_free"],
        "fps_ratio_bag_label_free": fps["bag_label_free"] / fps["anovox_label_free"],
        "fps_each_round": {side: [frames / s for s in times] for side, times in seconds.items()},
        "mib_per_frame": {side: size / frames / 2**20 for side, size in sizes.items()},
        "same_rgb": same_rgb,
        "same_lidar": same_lidar,
    }


def _read_all(open_side: Callable[[], Iterable], frames: int, side: str) -> float:
    """Seconds to open a drive and load every frame."""
    start = time.perf_counter()
    count = sum(1 for _ in open_side())
    seconds = time.perf_counter() - start
    if count != frames:
        raise RuntimeError(f"bench data: the {side} side read {count} frames; expected {frames}")
    return seconds


def _same_frames(anovox: Iterable, bag: Iterable) -> tuple[bool, bool]:
    """Whether every frame of both sides has the same camera pixels, and the same lidar points."""
    same_rgb = same_lidar = True
    for ours, theirs in zip(anovox, bag, strict=True):
        same_rgb &= np.array_equal(ours.rgb, theirs.rgb)
        same_lidar &= ours.lidar is not None and theirs.lidar is not None and np.array_equal(ours.lidar, theirs.lidar)
    return same_rgb, same_lidar


def _folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
