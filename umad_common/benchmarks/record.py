"""`umad bench record`: what the recording's guarantee costs, the default graph with and without
`--record`, side by side in one run.

The recorder acks every frame it has written (`umad_common/dataflow/record/recorder.py`), so a recorded run goes
no faster than its log is written. The same generated drive runs through the default graph
alternately without and with a recording (`pairs` times each, alternating, so a machine whose speed
drifts moves both sides alike); frames/s is the median per side, and `fps_ratio_recorded` their
ratio. Each recorded run's log is checked: every channel holds every frame (`complete`), and its
size and messages are reported.
"""

from __future__ import annotations

import statistics
import tempfile
from collections import defaultdict
from pathlib import Path

import yaml

from umad_common import DEFAULT_GRAPH
from umad_common.benchmarks.graphs import run_bench_graph
from umad_common.dataflow.api.messages import decode
from umad_common.dataflow.record.mcap_log import read_log, recording_outcome


def bench_record(
    frames: int = 30, pairs: int = 2, hub: str = "tcp/127.0.0.1:7449", graph: Path = DEFAULT_GRAPH
) -> dict:
    from umad_common.datasets.synthetic.generator import generate_benchmark

    work = Path(tempfile.mkdtemp(prefix="umad-bench-record-"))
    generate_benchmark(work / "data", 0, 1, frames, 1, (384, 256))
    graph_data = yaml.safe_load(Path(graph).read_text())
    graph_data["base_dir"] = str(Path(graph).resolve().parent)
    graph_data["hub"] = hub
    for op in graph_data["operators"]:
        if op.get("kind") == "replayer":
            op.setdefault("params", {}).update({"source": str(work / "data" / "anomalous"), "every": 1})
    runs: dict[str, list[dict]] = {"plain": [], "recorded": []}
    logs = []
    for index in range(pairs):
        runs["plain"].append(run_bench_graph(graph_data))
        log = work / f"run{index}.mcap"
        runs["recorded"].append(run_bench_graph(graph_data, record=log))
        logs.append(log_facts(log, frames))
        log.unlink()
    fps = {side: statistics.median(r["fps"] for r in results) for side, results in runs.items()}
    p99 = {side: statistics.median(r["p99_ms"] for r in results) for side, results in runs.items()}
    return {
        "frames": frames,
        "pairs": pairs,
        "fps_plain": fps["plain"],
        "fps_recorded": fps["recorded"],
        "fps_ratio_recorded": fps["recorded"] / fps["plain"],
        "end_to_end_p99_ms_plain": p99["plain"],
        "end_to_end_p99_ms_recorded": p99["recorded"],
        "fps_each_run": {side: [r["fps"] for r in results] for side, results in runs.items()},
        "log_mib_per_frame": statistics.median(f["bytes"] for f in logs) / frames / 2**20,
        "log_messages": logs[0]["messages"],
        "complete": all(f["complete"] for f in logs),
    }


def log_facts(log: Path, frames: int) -> dict:
    """A recorded run's log: its size, messages, and whether every channel holds every frame
    (and the end-of-run marker) and the recorder reported nothing lost."""
    seqs: dict[str, set[int]] = defaultdict(set)
    for message in read_log(log):
        seqs[message.topic].add(decode(message.data).seq)
    outcome = recording_outcome(log)
    every_frame = all(got >= set(range(frames + 1)) for got in seqs.values())
    return {
        "bytes": log.stat().st_size,
        "messages": sum(1 for _ in read_log(log)),
        "complete": every_frame and outcome is not None and not outcome["lost"] and not outcome["lacking"],
    }
