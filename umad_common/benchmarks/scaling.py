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

`umad bench scaling --op world_model` does the same for the world model, an ordered operator in
keyed replicas (`bench_world_model_scaling`): generated drives sent side by side, each computed by
one replica.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from pydantic import Field

from umad_common.benchmarks.graphs import run_bench_graph
from umad_common.benchmarks.pipeline import work_per_frame, work_with_every_core_busy
from umad_common.dataflow import Output, Source, SourceFrame, SourceParams
from umad_common.dataflow.api.graph import validate_graph


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
    """`frames` for the feature net and a tenth of them for the far heavier VGG16, so both runs
    last seconds: in a run under a second, filling and draining the 8 frames in flight is a
    large part of it and lowers the ratio (docs/experiments.md)."""
    vgg_frames = max(8, frames // 10)
    return {
        "frames": {"feature_net": frames, "vgg16": vgg_frames},
        "feature_net": compare_replicas(frames, hub),
        "vgg16": compare_replicas(vgg_frames, hub, random_vgg16_file()),
        "vgg16_weights": "random, torchvision layout (ImageNet weights cannot be downloaded here; same cost)",
    }


def world_model_scaling_graph(replicas: int, drives: Path, hub: str) -> dict:
    """The replayer sending every drive side by side to the world model in `replicas` keyed
    replicas (1 torch thread each), whose frames go to a sink."""
    runs = len(list(drives.glob("Scenario_*")))
    replayer = {"source": str(drives), "every": 1, "window": 4, "runs_in_flight": runs}
    return {
        "name": f"wm_scaling{replicas}",
        "hub": hub,
        "base_dir": str(Path.cwd()),
        "operators": [
            {"id": "replayer", "kind": "replayer", "params": replayer},
            {
                "id": "world_model",
                "kind": "world_model",
                "inputs": {
                    "camera": "replayer/camera",
                    "lidar": "replayer/lidar",
                    "ego": "replayer/ego",
                    "route": "replayer/route",
                },
                "replicas": replicas,
                "params": {"threads": 1},
            },
            {"id": "sink", "uses": "umad_common.benchmarks.bus:BlobSink", "inputs": {"blob": "world_model/frame"}},
        ],
    }


def bench_world_model_scaling(drives: int = 4, frames: int = 40, hub: str = "tcp/127.0.0.1:7449") -> dict:
    """The world model, an ordered operator, with 1 and with 2 keyed replicas on `drives` generated
    drives of `frames` frames sent side by side: each drive goes to one replica (rendezvous hashing
    of its name), so the ratio is bound by how evenly the drives fall (`drives_per_replica_with_2`;
    with 4 drives, 2 and 2 three times in eight). Next to it, the machine's own ratio as in
    `compare_replicas`: the same chain in one process, alone and in two processes at once."""
    from umad_common.dataflow.delivery.ordered import rendezvous_score
    from umad_common.datasets.synthetic.generator import generate_benchmark

    data = Path(tempfile.mkdtemp(prefix="umad-bench-wm-")) / "drives"
    generate_benchmark(data, 0, drives, frames, 0, (384, 256))
    drives_dir = data / "anomalous"
    single = world_model_scaling_graph(1, drives_dir, hub)
    one = run_bench_graph(single)
    two = run_bench_graph(world_model_scaling_graph(2, drives_dir, hub))
    owners: dict[str, list[str]] = {"r0": [], "r1": []}
    for drive in sorted(p.name for p in drives_dir.glob("Scenario_*")):
        owners[max(owners, key=lambda replica: rendezvous_score(drive, replica))].append(drive)
    alone = work_per_frame(validate_graph(single))
    together = work_with_every_core_busy(single, 2)
    return {
        "drives": drives,
        "frames_per_drive": frames,
        "replicas_1": {k: one[k] for k in ("fps", "p50_ms", "p99_ms")},
        "replicas_2": {k: two[k] for k in ("fps", "p50_ms", "p99_ms")},
        "frames_per_replica_with_2": {
            k: v["frames_in"] for k, v in two["stats"].items() if k.startswith("world_model")
        },
        "drives_per_replica_with_2": {replica: len(runs) for replica, runs in owners.items()},
        "fps_ratio_2_over_1": two["fps"] / one["fps"],
        "in_process_fps": {"alone": alone["fps"], "two_processes": [t["fps"] for t in together]},
        "in_process_ratio_2_over_1": sum(t["fps"] for t in together) / alone["fps"],
    }
