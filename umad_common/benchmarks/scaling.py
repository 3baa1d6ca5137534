"""`umad bench scaling`: the perceptual difference worker with 1 and with 2 replicas, side by side.

A source publishes world-model-shaped frames (128x192 target, reconstruction, 3 predictions) to a
`difference` operator with metric `perceptual` (1 torch thread per replica), whose maps go to a
sink. The ratio is frames/s with 2 replicas over frames/s with 1, on the same machine in one run,
for both extractors: the shipped label-free feature net (so light that the bus, not the worker,
sets the pace) and ImageNet VGG16 (the paper's; randomly initialised weights in torchvision's
format, which cost exactly what ImageNet ones do).

Next to each ratio, the machine's own: the same source, worker and sink in one process
(`work_per_frame`, no bus), once alone and then in two processes at once. Their frames/s together
over one's alone is what two cores give this work before any dataflow cost.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from pydantic import Field

from umad_common.benchmarks.graphs import run_bench_graph
from umad_common.benchmarks.pipeline import work_per_frame, work_with_every_core_busy
from umad_common.dataflow import Output, Source, SourceFrame, SourceParams
from umad_common.dataflow.graph import validate_graph


class WorldModelFrames(Source):
    """Random but fixed frames shaped like the world model's `frame` output."""

    kind = "bench_world_model_frames"
    outputs = ("frame",)

    class Params(SourceParams):
        frames: int = Field(40, description="frames to send")
        height: int = Field(128, description="image height")
        width: int = Field(192, description="image width")

    def frames(self):
        rng = np.random.default_rng(0)
        h, w = self.params.height, self.params.width
        target = rng.random((h, w, 3), dtype=np.float32)
        recon = np.clip(target + rng.normal(0, 0.05, (h, w, 3)).astype(np.float32), 0, 1)
        preds = np.stack([recon] * 3)
        for seq in range(self.params.frames):
            arrays = {"target": target, "recon": recon, "preds": preds, "pred_valid": np.ones(3, np.uint8)}
            yield SourceFrame("bench", seq, seq, {"frame": Output(arrays)})


def scaling_graph(replicas: int, frames: int, hub: str, vgg_weights: str | None = None) -> dict:
    params = {"metric": "perceptual", "threads": 1}
    if vgg_weights:
        params["vgg_weights"] = vgg_weights
    return {
        "name": f"scaling{replicas}",
        "hub": hub,
        "operators": [
            {"id": "frames", "uses": f"{__name__}:WorldModelFrames", "params": {"frames": frames}},
            {
                "id": "diff_perceptual",
                "kind": "difference",
                "inputs": {"frame": "frames/frame"},
                "replicas": replicas,
                "params": params,
            },
            {"id": "sink", "uses": "umad_common.benchmarks.bus:BlobSink", "inputs": {"blob": "diff_perceptual/map"}},
        ],
    }


def random_vgg16_file() -> str:
    """A torchvision-format VGG16 state dict with random weights, in a temporary file."""
    import torch

    from umad_common.models.vgg16 import Vgg16Features

    torch.manual_seed(0)
    path = Path(tempfile.mkdtemp(prefix="umad-bench-vgg-")) / "vgg16_random.pth"
    torch.save(Vgg16Features().state_dict(), path)
    return str(path)


def compare_replicas(frames: int, hub: str, vgg_weights: str | None = None) -> dict:
    single = scaling_graph(1, frames, hub, vgg_weights)
    one = run_bench_graph(single)
    two = run_bench_graph(scaling_graph(2, frames, hub, vgg_weights))
    per_replica = {k: v["frames_in"] for k, v in two["stats"].items() if k.startswith("diff_perceptual")}
    alone = work_per_frame(validate_graph(single))
    together = work_with_every_core_busy(single, 2)
    return {
        "replicas_1": {k: one[k] for k in ("fps", "p50_ms", "p99_ms")},
        "replicas_2": {k: two[k] for k in ("fps", "p50_ms", "p99_ms")},
        "frames_per_replica_with_2": per_replica,
        "fps_ratio_2_over_1": two["fps"] / one["fps"],
        "in_process_fps": {"alone": alone["fps"], "two_processes": [t["fps"] for t in together]},
        "in_process_ratio_2_over_1": sum(t["fps"] for t in together) / alone["fps"],
    }


def bench_scaling(frames: int = 400, hub: str = "tcp/127.0.0.1:7449") -> dict:
    """`frames` for the feature net, a tenth of them for VGG16 (10x its cost per frame), so both
    runs last seconds: with 40 feature-net frames a run lasted under a second, and filling and
    draining the 8 frames in flight took a fifth of it (2 over 1 replica: 1.55 there, 1.63 with 400
    frames, in the same session)."""
    vgg_frames = max(8, frames // 10)
    return {
        "frames": {"feature_net": frames, "vgg16": vgg_frames},
        "feature_net": compare_replicas(frames, hub),
        "vgg16": compare_replicas(vgg_frames, hub, random_vgg16_file()),
        "vgg16_weights": "random, torchvision layout (ImageNet weights cannot be downloaded here; same cost)",
    }
