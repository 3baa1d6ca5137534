"""`umad bench live`: the shipped live graph (UMAD alone, `umad launch --live`) on a generated drive
published at the camera's rate, and whether it keeps up.

One anomalous drive of the built-in world (seed 1, 384 x 256, `frames` long, so the stream never
pauses at a run's end) is replayed at `rate_hz` with `pacing: realtime`: the replayer publishes
whatever the graph keeps up with and never re-sends. A subscriber in this process, a client of the
graph's hub, notes when each frame's camera message, refined map and frame result arrive, on one
clock, and matches them by (run, seq). Reported:

- `fps_kept`: of the frames sent at the camera's rate (after `frames_primed`), those whose result
  arrived complete (not partial), over their wall time (the first one's camera message's arrival to
  the last result's), so a graph that falls behind is not flattered by a backlog it clears after
  the camera stopped, nor by the start-up frames it was sent faster than the camera's rate;
- `frames_partial` (fusion's live deadline, `deadline_ms`, passed without every difference map),
  `frames_dropped` (no result arrived, or a superseded marker: an operator passed the frame over for
  a newer one, `frames_superseded`) and `frames_failed` (an error marker arrived instead);
  `frames_missed` is their sum;
- `frames_primed`: frames the replayer sent one at a time at start-up, each once the one before was
  acked, until the graph answered three in a row within one camera period (at most 3 s): they are in every
  figure here but `fps_kept`, kept or not, but were not sent at the camera's rate;
- `latency_ms`: from the camera message's arrival to the refined map's (`camera_to_refined`) and to
  the frame result's (`camera_to_result`) at the same subscriber, p50 / p99 / max, over the frames
  where all three arrived. It leaves out
  the camera's own hop from the replayer to the subscriber (one bus hop: `umad bench bus`). Beside
  it the replayer's own send-to-ack latency (`source_send_to_ack_*`, the result operator's ack);
- `cpu_ms_per_frame`: per operator, its own work per frame it computed, and `runtime_cpu_ms` per
  frame the runtime's (decoding, joining, acks), from the replicas' stats as the launcher prints
  them; `queue_ms` shows the operator a frame waited for. `counts`: per replica, frames in and out,
  frames its joiner dropped, frames it passed over for a newer one (`superseded`) and ring payloads
  overwritten before it read them (`lost_payloads`).
"""

from __future__ import annotations

import os
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from umad_common import LIVE_GRAPH
from umad_common.benchmarks.graphs import run_bench_graph
from umad_common.benchmarks.pipeline import stage_times

COUNTS = ("frames_in", "frames_out", "dropped", "superseded", "lost_payloads", "errors")  # per replica, from its stats
WATCHED = {"camera": ("replayer", "camera"), "refined": ("refine", "refined"), "result": ("result", "result")}


@dataclass
class Arrivals:
    """When each watched output of each frame arrived here (time.monotonic), and the results' meta."""

    times: dict[str, dict[tuple[str, int], float]] = field(default_factory=lambda: {name: {} for name in WATCHED})
    result_meta: dict[tuple[str, int], dict] = field(default_factory=dict)
    unreadable: int = 0  # ring payloads overwritten before this subscriber read them
    lock: threading.Lock = field(default_factory=threading.Lock)


class ArrivalListener:
    """A client of the graph's hub, started before the graph and connecting once the hub is up,
    that subscribes to the camera, the refined map and the frame result."""

    def __init__(self, hub: str, graph_name: str):
        self.hub = hub
        self.graph_name = graph_name
        self.arrivals = Arrivals()
        self.stop = threading.Event()
        self.session = None
        self._thread = threading.Thread(target=self._connect, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _connect(self) -> None:
        from umad_common.dataflow.transport.bus import Keys, open_client
        from umad_common.dataflow.transport.planes import open_plane

        self.plane = open_plane()
        self.session = open_client(self.hub, cancel=self.stop)
        if self.session is None:
            return
        keys = Keys(self.graph_name)
        self.subscribers = [
            self.session.declare_subscriber(keys.data(op, output), self._callback(name))
            for name, (op, output) in WATCHED.items()
        ]

    def _callback(self, name: str):
        from umad_common.dataflow.api.messages import decode

        def on_sample(sample) -> None:
            arrived = time.monotonic()
            payload = self.plane.take(sample.payload.to_bytes())
            msg = None if payload is None else decode(payload)
            with self.arrivals.lock:
                if msg is None:
                    self.arrivals.unreadable += 1
                elif not msg.meta.get("eos"):
                    if not (msg.meta.get("error") or msg.meta.get("superseded")):  # a marker is no map: not timed
                        self.arrivals.times[name].setdefault((msg.run, msg.seq), arrived)
                    if name == "result":
                        self.arrivals.result_meta.setdefault((msg.run, msg.seq), msg.meta)

        return on_sample

    def close(self) -> Arrivals:
        self.stop.set()
        self._thread.join(timeout=30)
        if self.session is not None:
            from umad_common.dataflow.transport.bus import close_session

            close_session(self.session)
            self.plane.close()
        return self.arrivals


def bench_live(
    frames: int = 600, hub: str = "tcp/127.0.0.1:7449", rate_hz: float = 10.0, graph: Path = LIVE_GRAPH
) -> dict:
    from umad_common.datasets.synthetic.generator import generate_benchmark

    if frames < 2:
        raise ValueError(f"bench live: --frames {frames}; expected at least 2 (one drive of that many frames)")
    data = Path(tempfile.mkdtemp(prefix="umad-bench-data-"))
    generate_benchmark(data, 0, 1, frames, 1, (384, 256))
    graph_data = yaml.safe_load(Path(graph).read_text())
    graph_data["base_dir"] = str((Path(graph).parent / graph_data.get("base_dir", ".")).resolve())
    graph_data["hub"] = hub
    for op in graph_data["operators"]:
        if op.get("kind") == "replayer":
            op.setdefault("params", {}).update(
                {"source": str(data / "anomalous"), "every": 1, "pacing": "realtime", "rate_hz": rate_hz}
            )
    load_before = os.getloadavg()
    listener = ArrivalListener(hub, graph_data["name"])
    listener.start()
    try:
        result = run_bench_graph(graph_data)
    finally:
        arrivals = listener.close()
    stats = result["stats"]
    source = stats["replayer.r0"]
    return {
        "frames_sent": source["computed"],
        "rate_hz": rate_hz,
        "cores": len(os.sched_getaffinity(0)),
        "load_avg_1m_before": load_before[0],
        **frame_counts(arrivals, source["computed"], source["primed"]),
        "latency_ms": {
            "camera_to_refined": percentiles(latencies(arrivals, "refined")),
            "camera_to_result": percentiles(latencies(arrivals, "result")),
        },
        "frames_primed": source["primed"],
        "source_acked": source["acked"],
        "source_send_to_ack_p50_ms": source["p50_ms"],
        "source_send_to_ack_p99_ms": source["p99_ms"],
        "dropped_in_operators": sum(s.get("dropped", 0) for s in stats.values()),
        "unreadable_payloads": arrivals.unreadable,
        "wall_s_with_startup": result["wall_s_with_startup"],
        "cpu_ms_per_frame": {op: stage_times(stats, op) for op in sorted({name.rsplit(".", 1)[0] for name in stats})},
        "counts": {name: {k: replica.get(k, 0) for k in COUNTS} for name, replica in sorted(stats.items())},
    }


def frame_counts(arrivals: Arrivals, sent: int, primed: int) -> dict:
    """Results kept, partial, failed and dropped, and frames/s kept over the wall time of the frames
    sent at the camera's rate: all but the first `primed` (one drive, so its seq counts from 0)."""
    outcome = {  # markers carry no `partial`
        key: next((flag for flag in ("error", "superseded", "partial") if meta.get(flag)), "kept")
        for key, meta in arrivals.result_meta.items()
    }
    count = Counter(outcome.values())
    failed, superseded, partial = count["error"], count["superseded"], count["partial"]
    dropped = max(0, sent - len(outcome)) + superseded
    cameras = [t for (_, seq), t in arrivals.times["camera"].items() if seq >= primed]
    results = [t for (_, seq), t in arrivals.times["result"].items() if seq >= primed]
    stream_s = max(results) - min(cameras) if cameras and results else 0.0
    kept_at_rate = sum(1 for (_, seq), kind in outcome.items() if kind == "kept" and seq >= primed)
    return {
        "frames_kept": count["kept"],
        "frames_partial": partial,
        "frames_failed": failed,
        "frames_dropped": dropped,
        "frames_superseded": superseded,
        "frames_missed": partial + failed + dropped,
        "stream_s": stream_s,
        "fps_kept": kept_at_rate / stream_s if stream_s > 0 else 0.0,
    }


def latencies(arrivals: Arrivals, name: str) -> list[float]:
    """ms from each frame's camera message to its `name` message, over the frames where the camera,
    the refined map and the result all arrived: both figures describe the same frames, so the
    result's percentiles are never below the refined map's."""
    camera, refined, result = (arrivals.times[n] for n in ("camera", "refined", "result"))
    return [
        1e3 * (t - camera[key])
        for key, t in arrivals.times[name].items()
        if key in camera.keys() & refined.keys() & result.keys()
    ]


def percentiles(values_ms: list[float]) -> dict:
    if not values_ms:
        return {"frames": 0, "p50": None, "p99": None, "max": None}
    values = np.asarray(values_ms)
    return {
        "frames": len(values),
        "p50": float(np.percentile(values, 50)),
        "p99": float(np.percentile(values, 99)),
        "max": float(values.max()),
    }
