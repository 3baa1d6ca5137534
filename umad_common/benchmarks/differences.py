"""`umad bench differences`: frames/s of each difference metric at the world model's size, in-process.

Every metric gets the same fixed world-model-shaped frame (192x128 target, reconstruction, three
past predictions; for the lidar metric 7,500 returns, about what the built-in lidar lands in the
camera's view) and one torch thread, as one `difference` replica has; each is timed over the
same number of frames in one run, so the ratios to `abs` (the cheapest) are what to compare.
"""

from __future__ import annotations

import time

import numpy as np

from umad_common import ASSETS
from umad_common.differences import METRICS, MetricOptions, RangePairs, build_metric, minmax

WARMUP_FRAMES = 2


def world_model_frame(height: int = 128, width: int = 192, horizon: int = 3, seed: int = 0) -> tuple:
    """(target, recon, preds, pred_valid) of the `frame` contract: random but fixed."""
    rng = np.random.default_rng(seed)
    target = rng.random((height, width, 3), dtype=np.float32)
    recon = np.clip(target + rng.normal(0, 0.05, target.shape), 0, 1).astype(np.float32)
    preds = np.stack([np.clip(recon + rng.normal(0, 0.02, recon.shape), 0, 1) for _ in range(horizon)])
    return target, recon, preds.astype(np.float32), np.ones(horizon, np.uint8)


def lidar_pairs(height: int = 128, width: int = 192, returns: int = 7500, seed: int = 0) -> RangePairs:
    """Returns at random pixels, measured and expected ranges of the `frame` contract: random but fixed."""
    rng = np.random.default_rng(seed)
    pixel = np.stack([rng.integers(0, height, returns), rng.integers(0, width, returns)], axis=1).astype(np.int32)
    expected = rng.uniform(3.0, 80.0, returns).astype(np.float32)
    return RangePairs(pixel, (expected * rng.uniform(0.5, 1.2, returns)).astype(np.float32), expected)


def bench_differences(frames: int = 20, height: int = 128, width: int = 192) -> dict:
    import torch

    torch.set_num_threads(1)
    arrays = world_model_frame(height, width)
    lidar = lidar_pairs(height, width)
    options = MetricOptions(features=ASSETS / "feature_net.safetensors")
    fps: dict[str, float] = {}
    for name in METRICS:
        metric = build_metric(name, options)
        for _ in range(WARMUP_FRAMES):
            minmax(metric(*arrays, lidar=lidar))
        start = time.perf_counter()
        for _ in range(frames):
            minmax(metric(*arrays, lidar=lidar))
        fps[name] = frames / (time.perf_counter() - start)
    return {
        "frames": frames,
        "size": f"{width}x{height}",
        "fps": fps,
        "ms_per_frame": {name: 1e3 / value for name, value in fps.items()},
        "fps_ratio_to_abs": {name: value / fps["abs"] for name, value in fps.items()},
    }
