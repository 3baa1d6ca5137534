"""`umad bench segmenters`: ms/frame and anomaly isolation of each segmenter method on labelled drives.

    umad bench segmenters [--data DIR] [--tune] [--world-model MODEL.safetensors]

Without `--data`, two anomalous drives of the built-in world are generated (a seed the shipped
models never saw). The figures are defined in `umad_common.benchmarks.segmentation_quality`;
`tune` measures a small grid around each method's defaults (the grid that chose the defaults in
operators/segmenter.py); a world model adds the pixel AP after mean refinement of abs+ssim maps.
"""

from __future__ import annotations

import itertools
import tempfile
from pathlib import Path

METHODS = ("gt", "felzenszwalb", "slic", "kmeans")

TUNING_GRID: dict[str, dict[str, list]] = {
    "gt": {"gt_stuff": [True, False]},
    "felzenszwalb": {"felzenszwalb_scale": [50.0, 100.0, 200.0], "felzenszwalb_sigma": [0.3, 0.8]},
    "slic": {"slic_n_segments": [100, 200, 300], "slic_compactness": [10.0, 20.0]},
    "kmeans": {"kmeans_clusters": [16, 32, 48], "kmeans_position_weight": [0.25, 0.5]},
}
BUILTIN_DRIVES, BUILTIN_FRAMES, BUILTIN_SEED = 2, 60, 1


def configurations(methods: list[str], tune: bool) -> list[dict]:
    """The parameter sets to measure: each method's defaults, or its tuning grid."""
    configs = []
    for method in methods:
        grid = TUNING_GRID[method] if tune else {}
        names = list(grid)
        for values in itertools.product(*(grid[n] for n in names)):
            configs.append({"method": method, **dict(zip(names, values, strict=True))})
    return configs


def bench_segmenters(
    data: Path | None = None,
    methods: list[str] | None = None,
    every: int = 1,
    max_frames: int = 0,
    tune: bool = False,
    world_model: Path | None = None,
) -> dict:
    from threadpoolctl import threadpool_limits

    from umad_common.benchmarks.segmentation_quality import anovox_frames, measure_segmenter

    if data is None:
        from umad_common.datasets.synthetic.generator import generate_benchmark

        data = Path(tempfile.mkdtemp(prefix="umad-bench-segmenters-"))
        generate_benchmark(data, 0, BUILTIN_DRIVES, BUILTIN_FRAMES, BUILTIN_SEED, (384, 256))
    root = data / "anomalous" if (data / "anomalous").is_dir() else data
    threadpool_limits(1)  # one core, as in a deployed replica
    frames = []
    for sample in anovox_frames(root, every=every, world_model=world_model):
        frames.append(sample)
        if max_frames and len(frames) >= max_frames:
            break
    print(f"{len(frames)} anomalous frames from {root}", flush=True)
    rows = {}
    for params in configurations(methods or list(METHODS), tune):
        quality = measure_segmenter(params, frames)
        print(quality.row(), flush=True)
        name = ",".join(f"{k}={v}" for k, v in params.items() if k != "method")
        rows[params["method"] + (f"[{name}]" if name else "")] = {
            k: v for k, v in vars(quality).items() if k != "params" and v is not None
        }
    return {"data": str(root), "frames": len(frames), "methods": rows}
