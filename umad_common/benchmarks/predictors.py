"""`umad bench predictors`: frames/s of the world-model predictor and the MNAD baseline, in-process.

Both operators run on the same generated drive (the built-in world at its default 384x256 camera,
plainly resized to each model's 192x128), frame by frame as the runtime would call them, with 1
and with 2 torch threads. The world model's first frames are warm-up (no predictions yet), so
timing starts after `WARMUP_FRAMES`.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from umad_common.dataflow import SourceFrame
from umad_common.dataflow.api.operator import frame_of

WARMUP_FRAMES = 4


def drive_frames(frames: int) -> list[SourceFrame]:
    """The replayer's frames of one generated anomalous drive."""
    from umad_common.datasets.synthetic.generator import generate_benchmark
    from umad_operators.replayer import Replayer

    data = Path(tempfile.mkdtemp(prefix="umad-bench-predictors-"))
    generate_benchmark(data, 0, 1, frames, 1, (384, 256))
    replayer = Replayer({"source": str(data / "anomalous")})
    return list(replayer.frames())


def frames_per_second(operator, frames: list[SourceFrame], ports: tuple[str, ...]) -> float:
    for sf in frames[:WARMUP_FRAMES]:
        operator.process(frame_of(sf.outputs, ports, sf.run, sf.seq))
    start = time.perf_counter()
    for sf in frames[WARMUP_FRAMES:]:
        operator.process(frame_of(sf.outputs, ports, sf.run, sf.seq))
    return (len(frames) - WARMUP_FRAMES) / (time.perf_counter() - start)


def bench_predictors(frames: int = 40) -> dict:
    import torch

    from umad_operators.mnad import MnadPredictor
    from umad_operators.world_model import WorldModelPredictor

    drive = drive_frames(frames + WARMUP_FRAMES)
    result: dict = {"frames": len(drive) - WARMUP_FRAMES, "camera": "384x256", "model_size": "192x128"}
    for threads in (1, 2):
        world_model = WorldModelPredictor({"threads": threads})
        wm_fps = frames_per_second(world_model, drive, ("camera", "lidar", "ego", "route"))
        mnad_fps = frames_per_second(MnadPredictor({"threads": threads}), drive, ("camera",))
        result[f"threads_{threads}"] = {"world_model_fps": wm_fps, "mnad_fps": mnad_fps}
    torch.set_num_threads(1)
    result["world_model_fps_ratio_2_over_1_threads"] = (
        result["threads_2"]["world_model_fps"] / result["threads_1"]["world_model_fps"]
    )
    return result
