"""`umad bench pipeline`: the default graph end to end on a small generated benchmark.

Reports frames/s (frames over the source's first-send-to-last-ack time, start-up excluded) and the
end-to-end latency from the replayer's send to the accumulator's ack (p50/p99), plus each operator's
own processing latency, so the slowest stage is visible.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import yaml

from umad_common import DEFAULT_GRAPH
from umad_common.benchmarks.graphs import run_bench_graph


def bench_pipeline(frames: int = 30, hub: str = "tcp/127.0.0.1:7449", graph: Path = DEFAULT_GRAPH) -> dict:
    from umad_common.datasets.synthetic.generator import generate_benchmark

    data = Path(tempfile.mkdtemp(prefix="umad-bench-data-"))
    generate_benchmark(data, 0, 1, frames, 1, (384, 256))
    graph_data = yaml.safe_load(Path(graph).read_text())
    graph_data["base_dir"] = str(Path(graph).resolve().parent)
    graph_data["hub"] = hub
    for op in graph_data["operators"]:
        if op.get("kind") == "replayer":
            op.setdefault("params", {}).update({"source": str(data / "anomalous"), "every": 1})
    result = run_bench_graph(graph_data)
    stages = {
        name.rsplit(".", 1)[0]: {"p50_ms": s["p50_ms"], "p99_ms": s["p99_ms"]}
        for name, s in result["stats"].items()
        if not name.startswith(graph_data["operators"][0]["id"])
    }
    return {
        "frames": result["frames"],
        "fps": result["fps"],
        "end_to_end_p50_ms": result["p50_ms"],
        "end_to_end_p99_ms": result["p99_ms"],
        "wall_s_with_startup": result["wall_s_with_startup"],
        "stage_latency": stages,
    }
