"""Run a benchmark graph with the launcher and read the source's pacing stats back."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import yaml


def run_bench_graph(graph_data: dict, timeout_note: str = "", record: Path | None = None) -> dict:
    """Launch `graph_data` quietly (recorded to `record` if given); returns the source's frames/s
    and send-to-ack latency."""
    from umad_common.dataflow.api.graph import load_graph
    from umad_common.dataflow.launch.launcher import Launcher

    path = Path(tempfile.mkdtemp(prefix="umad-bench-")) / "graph.yaml"
    path.write_text(yaml.safe_dump(graph_data, sort_keys=False))
    graph = load_graph(path)
    launcher = Launcher(graph, path, record=record, quiet=True)
    start = time.perf_counter()
    code = launcher.run()
    wall = time.perf_counter() - start
    if code != 0:
        raise RuntimeError(f"benchmark graph {graph.name} failed with exit code {code} {timeout_note}")
    source = launcher.stats[f"{graph.sources()[0]}.r0"]
    frames = source["acked"]  # frames through every sink (end-of-run markers not counted)
    busy = source.get("busy_s") or wall
    return {
        "frames": frames,
        "fps": frames / busy,
        "p50_ms": source["p50_ms"],
        "p99_ms": source["p99_ms"],
        "wall_s_with_startup": wall,
        "start_and_stop_s": wall - busy,  # launch to the first frame sent, and the last ack to every replica gone
        "stats": launcher.stats,
        "hub_cpu_s": launcher.hub_cpu_s,  # its whole life, start-up included
    }
