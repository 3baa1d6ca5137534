"""`umad data info PATH`: what UMAD reads of a folder of drives, as `ros2 bag info` does for a bag.

For each drive (an AnoVox folder, a ROS 2 bag, a Foxglove MCAP): its frames, duration and rate; for
a recording, the topic each role reads and why it was chosen (named with `--topics`, or the only one
of its type); and what is missing and what that means (no lidar: `diff_lidar` and the `geometry`
masks cannot run; no labels: `umad eval` refuses the drive, `umad launch` runs it). A benchmark
folder's normal/ (training) and anomalous/ (evaluation) parts are listed apart. Bad input (no camera,
two candidates for a role, a recording cut off by a crash) is one line and exit code 2.

example: umad data info drives/ --topics camera=/front/image_raw,lidar=/velodyne_points
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from umad_common.commands.checks import drive_paths, opened
from umad_common.commands.common import add_topics_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = __doc__
    parser.add_argument("path", type=Path, help="a drive, or a folder of drives")
    add_topics_argument(parser)
    parser.add_argument(
        "--allow-truncated", action="store_true", help="read a recording cut off by a crash up to the damage"
    )
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")


def run(args: argparse.Namespace) -> int:
    parts = [
        ("normal drives (training)", args.path / "normal"),
        ("anomalous drives (evaluation)", args.path / "anomalous"),
    ]
    parts = [(title, folder) for title, folder in parts if folder.is_dir()] or [("drives", args.path)]
    found = {
        title: opened(
            drive_paths(folder, str(folder)), "PATH", topics=args.topics, allow_truncated=args.allow_truncated
        )
        for title, folder in parts
    }
    infos = {title: [drive.info() for drive in drives] for title, drives in found.items()}
    if args.json:
        print(json.dumps(infos, indent=2))
        return 0
    for title, drives in infos.items():
        print(f"{title}: {len(drives)}, {sum(d['frames'] for d in drives)} frames")
        for info in drives:
            print(f"\n  {info['name']}  ({info['format']}: {info['path']})")
            rate = f"{info['rate_hz']:.2f} Hz" if info["rate_hz"] else "one frame"
            print(
                f"    frames {info['frames']}, {info['duration_s']:.2f} s at {rate}; has {', '.join(info['modalities'])}"
            )
            for role, choices in info.get("roles", {}).items():
                for choice in choices:
                    print(
                        f"    {role:<12}{choice['topic']}  {choice['type']}  {choice['messages']} messages  "
                        f"({choice['why']})"
                    )
            for note in info["notes"]:
                print(f"    note: {note}")
        print()
    return 0
