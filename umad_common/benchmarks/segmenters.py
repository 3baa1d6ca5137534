"""`umad bench segmenters`: ms/frame and anomaly isolation of each segmenter method on labelled drives.

    umad bench segmenters [--data DIR] [--tune] [--world-model MODEL.safetensors] [--seed 2]

The methods are the registry's (`umad_common.segmentation.SEGMENTERS`); a method whose defaults
cannot run here (SAM without a checkpoint) is listed as skipped with the reason. Without `--data`,
two anomalous drives of the built-in world are generated on the validation seed (2): the shipped
models train on seed 0 and `umad eval` evaluates seed 1, so every default chosen with labels here
(`--tune` measures each method's `tuning_grid`) is chosen on drives the evaluation never sees. The
figures are defined in `umad_common.benchmarks.segmentation_quality`; a world model adds the pixel
AP after mean refinement of its abs+ssim maps, next to the ground-truth masks' (`gt`).
"""

from __future__ import annotations

import itertools
import tempfile
from pathlib import Path

VALIDATION_SEED = 2  # neither the training seed (0) nor the evaluation seed (1)
BUILTIN_DRIVES, BUILTIN_FRAMES = 2, 60


def configurations(methods: list[str], tune: bool) -> list[dict]:
    """The segmenter parameters to measure: each method's defaults, or its tuning grid."""
    from umad_common.segmentation import segmenter_class

    configs = []
    for method in methods:
        grid = segmenter_class(method).tuning_grid if tune else {}
        names = list(grid)
        for values in itertools.product(*(grid[n] for n in names)):
            configs.append({"method": method, "options": dict(zip(names, values, strict=True))})
    return configs


def bench_segmenters(
    data: Path | None = None,
    methods: list[str] | None = None,
    every: int = 1,
    max_frames: int = 0,
    tune: bool = False,
    world_model: Path | None = None,
    seed: int = VALIDATION_SEED,
) -> dict:
    from threadpoolctl import threadpool_limits

    from umad_common.benchmarks.segmentation_quality import anovox_frames, measure_segmenter
    from umad_common.segmentation import SEGMENTERS

    generated = data is None
    if generated:
        from umad_common.datasets.synthetic.generator import generate_benchmark

        data = Path(tempfile.mkdtemp(prefix="umad-bench-segmenters-"))
        generate_benchmark(data, 0, BUILTIN_DRIVES, BUILTIN_FRAMES, seed, (384, 256))
        print(f"generated {BUILTIN_DRIVES} anomalous drives of the built-in world, seed {seed}", flush=True)
    else:
        print(f"drives from {data} (seed: whatever made them; the built-in validation seed is {VALIDATION_SEED})")
    root = data / "anomalous" if (data / "anomalous").is_dir() else data
    threadpool_limits(1)  # one core, as in a deployed replica
    frames = []
    for sample in anovox_frames(root, every=every, world_model=world_model):
        frames.append(sample)
        if max_frames and len(frames) >= max_frames:
            break
    print(f"{len(frames)} anomalous frames from {root}", flush=True)
    rows, skipped = {}, {}
    for params in configurations(methods or list(SEGMENTERS), tune):
        try:
            quality = measure_segmenter(params, frames)
        except (ValueError, ImportError, OSError) as exc:
            skipped[params["method"]] = f"{type(exc).__name__}: {exc}"
            print(f"skipped {params['method']}: {exc}", flush=True)
            continue
        print(quality.row(), flush=True)
        name = ",".join(f"{k}={v}" for k, v in params["options"].items())
        rows[params["method"] + (f"[{name}]" if name else "")] = {
            k: v for k, v in vars(quality).items() if k != "params" and v is not None
        }
    return {"data": str(root), "seed": seed if generated else None, "frames": len(frames), "methods": rows} | (
        {"skipped": skipped} if skipped else {}
    )
