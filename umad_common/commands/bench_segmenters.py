"""Segmenter benchmark: ms/frame and anomaly isolation of each segmenter method on labelled drives.

    python -m umad_common.commands.bench_segmenters --data data/synth/anomalous [--tune]
        [--world-model umad_common/assets/world_model.safetensors] [--json out.json]

Figures are defined in `umad_common.segmentation_quality`; `--tune` adds a small grid around each
method's defaults (the grid that chose the defaults in operators/segmenter.py).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

METHODS = ("gt", "felzenszwalb", "slic", "kmeans")

TUNING_GRID: dict[str, dict[str, list]] = {
    "gt": {"gt_stuff": [True, False]},
    "felzenszwalb": {"felzenszwalb_scale": [50.0, 100.0, 200.0], "felzenszwalb_sigma": [0.3, 0.8]},
    "slic": {"slic_n_segments": [100, 200, 300], "slic_compactness": [10.0, 20.0]},
    "kmeans": {"kmeans_clusters": [16, 32, 48], "kmeans_position_weight": [0.25, 0.5]},
}


def configurations(methods: list[str], tune: bool) -> list[dict]:
    """The parameter sets to measure: each method's defaults, or its tuning grid."""
    configs = []
    for method in methods:
        grid = TUNING_GRID[method] if tune else {}
        names = list(grid)
        for values in itertools.product(*(grid[n] for n in names)):
            configs.append({"method": method, **dict(zip(names, values, strict=True))})
    return configs


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="folder holding anomalous Scenario_* folders")
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS), help="methods to measure")
    parser.add_argument("--every", type=int, default=1, help="use every n-th frame of each scenario")
    parser.add_argument("--max-frames", type=int, default=0, help="stop after this many anomalous frames (0 = all)")
    parser.add_argument("--tune", action="store_true", help="measure a small parameter grid per method")
    parser.add_argument(
        "--world-model",
        type=Path,
        help="also measure pixel AP after mean refinement, on abs+ssim maps of this world model (safetensors)",
    )
    parser.add_argument("--json", type=Path, help="also write the rows as JSON here")


def run(args: argparse.Namespace) -> int:
    from threadpoolctl import threadpool_limits

    from umad_common.segmentation_quality import anovox_frames, measure_segmenter

    threadpool_limits(1)  # one core, as in a deployed replica; the machine is shared
    frames = []
    for sample in anovox_frames(args.data, every=args.every, world_model=args.world_model):
        frames.append(sample)
        if args.max_frames and len(frames) >= args.max_frames:
            break
    print(f"{len(frames)} anomalous frames from {args.data}")
    rows = []
    for params in configurations(args.methods, args.tune):
        quality = measure_segmenter(params, frames)
        print(quality.row(), flush=True)
        rows.append(quality)
    if args.json:
        args.json.write_text(json.dumps([vars(r) for r in rows], indent=1))
    return 0


if __name__ == "__main__":
    cli = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(cli)
    sys.exit(run(cli.parse_args()))
