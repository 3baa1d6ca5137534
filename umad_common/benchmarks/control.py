"""`umad bench control`: how long `umad set` takes to come back with the full default graph running
(frames flowing, every core busy) against the same graph idle (its source holding its frames back).

A round trip is the user's whole command: a new `umad set fusion.weights.abs=...` process, from
its start to its exit once every replica answered. Beside it, the query alone on a session kept
open, which is what the command costs beyond starting Python.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from umad_common import DEFAULT_GRAPH
from umad_common.dataflow.api.graph import load_graph

READY_TIMEOUT_S = 300.0  # the default graph's operators load their models on a busy machine
QUERY_TIMEOUT_S = 30.0


def bench_control(
    rounds: int = 20, hub: str = "tcp/127.0.0.1:7449", data: Path | None = None, graph: Path = DEFAULT_GRAPH
) -> dict:
    if data is None:
        from umad_common.datasets.synthetic.generator import generate_benchmark

        data = Path(tempfile.mkdtemp(prefix="umad-bench-data-")) / "drives"
        generate_benchmark(data, 0, 2, 100, 1, (384, 256))
    source = str(Path(data).resolve())
    idle = _measure(
        graph, hub, [f"replayer.source={source}", "replayer.pacing=realtime", "replayer.rate_hz=0.001"], rounds, False
    )
    loaded = _measure(graph, hub, [f"replayer.source={source}"], rounds, True)
    return {
        "rounds": rounds,
        "idle": idle,
        "loaded": loaded,
        "command_p99_loaded_over_idle": loaded["command_p99_s"] / idle["command_p99_s"],
    }


def _measure(graph: Path, hub: str, sets: list[str], rounds: int, busy: bool) -> dict:
    """Launch `graph`, wait until every operator is live (and, `busy`, frames flow), then time
    `rounds` commands; rounds stop early when a busy graph runs out of frames."""
    from umad_common.dataflow.transport.bus import Keys, ask, open_client

    spec = load_graph(graph).spec
    launch = [sys.executable, "-m", "umad_common.cli", "launch", str(graph), "--hub", hub]
    proc = subprocess.Popen(
        launch + [a for s in sets for a in ("--set", s)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    session = open_client(hub, timeout_s=READY_TIMEOUT_S)
    if session is None:
        proc.kill()
        raise RuntimeError(f"bench control: no hub at {hub}")
    keys = Keys(spec.name)
    fusion_in: list[int] = [0]
    stats = session.declare_subscriber(
        f"{keys.root}/_stats/fusion/**", lambda s: fusion_in.append(json.loads(s.payload.to_bytes())["frames_in"])
    )
    try:
        _wait_ready(session, keys, {op.id for op in spec.operators}, busy, fusion_in, proc)
        commands, queries, failed = [], [], 0
        for i in range(rounds):
            if proc.poll() is not None:
                break
            value = (0.1, 0.3)[i % 2]
            start = time.perf_counter()
            done = subprocess.run(
                [sys.executable, "-m", "umad_common.cli", "set", f"fusion.weights.abs={value}", "--connect", hub],
                capture_output=True,
                text=True,
            )
            commands.append(time.perf_counter() - start)
            failed += done.returncode != 0
            start = time.perf_counter()
            answers = ask(session, keys.control("fusion"), {"set": {"weights.mse": value}}, QUERY_TIMEOUT_S)
            queries.append(time.perf_counter() - start)
            failed += not answers or any(a["status"] != "applied" for a in answers)
        frames_meanwhile = fusion_in[-1]
    finally:
        stats.undeclare()
        session.close()
        proc.send_signal(signal.SIGINT)  # as a user stops it
        proc.wait(timeout=120)
    cmd, query = np.array(commands), np.array(queries) * 1e3
    return {
        "rounds": len(commands),
        "failed": failed,
        "command_p50_s": float(np.percentile(cmd, 50)),
        "command_p99_s": float(np.percentile(cmd, 99)),
        "query_p50_ms": float(np.percentile(query, 50)),
        "query_p99_ms": float(np.percentile(query, 99)),
        "fusion_frames_in_at_end": frames_meanwhile,
    }


def _wait_ready(session, keys, wanted: set[str], busy: bool, fusion_in: list[int], proc: subprocess.Popen) -> None:
    """Every operator holds its liveliness token and, for the busy graph, fusion has seen frames."""
    from umad_common.dataflow.transport.bus import live_replicas

    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline and proc.poll() is None:
        live = {op for op, _ in live_replicas(session, keys)}
        if wanted <= live and (not busy or fusion_in[-1] > 0):
            return
        time.sleep(0.5)
    raise RuntimeError(f"bench control: the graph did not get ready within {READY_TIMEOUT_S:.0f}s")
