"""`umad bench bus --against dora`: the bus bench's relay as a dora-rs dataflow, for a rate to hold
UMAD's bus against.

The same chain as `bench.bus.over_bus`: a source sends `frames` blobs of `size_bytes` (pyarrow
arrays; dora moves them through its shared memory), a relay reads every byte of each
(`blobs.checksum`) and passes it on, a sink acks each frame to the source through a cycle, and the
source keeps at most `window` frames un-acked. The nodes run at the operators' CPU priority, as the
launcher runs UMAD's. Each node process runs `main` of this module with its role.

Two settings of dora (`over_dora(lossless=...)`):
- lossless: every input has `queue_policy: backpressure` and a queue of `window` frames, so a full
  queue holds its sender instead of dropping. dora 1.1 then routes every message through its
  daemon.
- blocking publishers: dora's default queues (which drop the oldest input when full), its nodes'
  Zenoh publishers set to block instead of dropping and their shared-memory pools sized for
  `window` frames: payloads go node to node through shared memory, read in place. On a busy
  2-core machine this setting still loses a few frames in some runs; the source then reports them
  (`lost_frames`) instead of waiting for ever, and its rate counts up to the last ack.

dora-rs is an optional extra (`pip install umad[dora]`: `dora-rs` and `dora-rs-cli`);
`dora_missing` says in one line when it is not installed.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from umad_common.benchmarks.blobs import checksum
from umad_common.dataflow.launch.replicas import OPERATOR_NICENESS

START_TIMEOUT_S = 120.0  # dora's own start-up (daemon, node handshakes) on a busy machine
PROBE = -1  # the seq of the frames the source sends until the chain answers
PROBE_INTERVAL_S = 0.5
ACK_TIMEOUT_S = 10.0  # no ack for this long: the frames still un-acked are lost


def dora_cli() -> str | None:
    """The `dora` command beside this interpreter, or on PATH."""
    beside = Path(sys.executable).parent / "dora"
    return str(beside) if beside.is_file() else shutil.which("dora")


def dora_missing() -> str | None:
    """Why the dora-rs relay cannot run here, in one line; None when it can."""
    try:
        import dora  # noqa: F401
    except ImportError:
        return "dora-rs is not installed (pip install 'umad[dora]'): the relay against dora-rs is not run"
    if dora_cli() is None:
        return "dora-rs-cli is not installed (pip install 'umad[dora]'): the relay against dora-rs is not run"
    return None


BLOCKING_PUBLISHERS = '{qos: {publication: [{key_exprs: ["**"], config: {congestion_control: "block"}}]}}'


def dataflow(frames: int, size_bytes: int, window: int, results: Path, lossless: bool) -> dict:
    """The dataflow descriptor: three nodes running this module (`lossless`: as the module says)."""
    policy = {"queue_policy": "backpressure"} if lossless else {}
    settings = {}
    if not lossless:
        overlay = results / "zenoh-overlay.json5"
        overlay.write_text(BLOCKING_PUBLISHERS)
        settings = {
            "DORA_ZENOH_CONFIG_OVERLAY": str(overlay),
            "DORA_NODE_SHM_POOL_SIZE": str((window + 1) * size_bytes),
        }

    def node(role: str, inputs: dict[str, str], outputs: list[str]) -> dict:
        return {
            "id": role,
            "path": sys.executable,
            "args": f"-m {__name__} {role}",
            "inputs": {name: {"source": source, "queue_size": window, **policy} for name, source in inputs.items()},
            "outputs": outputs,
            "env": {
                "UMAD_DORA_FRAMES": str(frames),
                "UMAD_DORA_SIZE": str(size_bytes),
                "UMAD_DORA_WINDOW": str(window),
                "UMAD_DORA_RESULTS": str(results),
                **settings,
            },
        }

    return {
        "nodes": [
            node("source", {"ack": "sink/ack"}, ["blob"]),
            node("relay", {"blob": "source/blob"}, ["blob"]),
            node("sink", {"blob": "relay/blob"}, ["ack"]),
        ]
    }


def over_dora(frames: int, size_bytes: int, window: int, lossless: bool = True) -> dict:
    """Run the relay with `dora run`; latency is send-to-ack at the source, CPU the three nodes'
    from their first frame on (dora's daemon, like UMAD's hub, not counted: `daemon_cpu_ms_per_frame`,
    start-up included)."""
    cli = dora_cli()
    assert cli is not None, dora_missing()
    with tempfile.TemporaryDirectory(prefix="umad-bench-dora-") as scratch:
        folder = Path(scratch)
        descriptor = folder / "relay.yml"
        descriptor.write_text(yaml.safe_dump(dataflow(frames, size_bytes, window, folder, lossless)))
        before = os.times()
        done = subprocess.run(
            [cli, "run", str(descriptor)],
            cwd=folder,
            capture_output=True,
            text=True,
            timeout=START_TIMEOUT_S + frames,
            preexec_fn=lambda: os.nice(OPERATOR_NICENESS),
        )
        after = os.times()
        found = {role: folder / f"{role}.json" for role in ("source", "relay", "sink")}
        missing = [role for role, path in found.items() if not path.is_file()]
        if missing:
            tail = (done.stdout + done.stderr)[-6000:]
            raise RuntimeError(f"dora run exited {done.returncode} without results from {missing}:\n{tail}")
        measured = {role: json.loads(path.read_text()) for role, path in found.items()}
    source = measured["source"]
    lat = np.array(source["latencies_s"]) * 1e3
    nodes_cpu_s = sum(values["cpu_s"] for values in measured.values())
    all_cpu_s = (after.children_user + after.children_system) - (before.children_user + before.children_system)
    acked = len(lat)
    return {
        "fps": acked / source["busy_s"],
        "p50_ms": float(np.percentile(lat, 50)),
        "p99_ms": float(np.percentile(lat, 99)),
        "cpu_ms_per_frame": 1e3 * nodes_cpu_s / acked,
        "daemon_cpu_ms_per_frame": 1e3 * max(0.0, all_cpu_s - nodes_cpu_s) / acked,
        "lost_frames": frames - acked,
    }


def _write_result(role: str, values: dict) -> None:
    Path(os.environ["UMAD_DORA_RESULTS"], f"{role}.json").write_text(json.dumps(values))


def run_source(node, frames: int, size_bytes: int, window: int) -> None:
    """Send `frames` blobs, at most `window` un-acked; a frame not acked within `ACK_TIMEOUT_S` of
    the last ack is lost, and the source stops waiting for it."""
    import pyarrow as pa

    blob = pa.array(np.random.default_rng(0).integers(0, 255, size_bytes, dtype=np.uint8))
    _wait_for_chain(node, blob)
    sent: dict[int, float] = {}
    latencies: list[float] = []
    start, cpu_start = time.perf_counter(), time.process_time()
    last_ack = start
    for seq in range(frames):
        if len(sent) >= window:
            if not _take_ack(node, sent, latencies):
                break
            last_ack = time.perf_counter()
        sent[seq] = time.perf_counter()
        node.send_output("blob", blob, {"seq": seq})
    while len(latencies) < frames and _take_ack(node, sent, latencies):
        last_ack = time.perf_counter()
    cpu_s = time.process_time() - cpu_start
    _write_result("source", {"busy_s": last_ack - start, "cpu_s": cpu_s, "latencies_s": latencies})


def _wait_for_chain(node, blob) -> None:
    """Send probes (seq -1) until one comes back acked: what a node sends before the next one has
    subscribed is lost, so the frames start once the whole chain is up."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        node.send_output("blob", blob, {"seq": PROBE})
        event = node.next(timeout=PROBE_INTERVAL_S)
        if event is not None and event["type"] == "INPUT" and event["metadata"]["seq"] == PROBE:
            return
    raise RuntimeError(f"dora relay: no probe came back within {START_TIMEOUT_S:.0f} s")


def _take_ack(node, sent: dict[int, float], latencies: list[float]) -> bool:
    """Wait for the next frame's ack; False when none came within `ACK_TIMEOUT_S` (frames lost)."""
    while True:
        event = node.next(timeout=ACK_TIMEOUT_S)
        if event is None or event["type"] != "INPUT":
            return False
        seq = event["metadata"]["seq"]
        if seq in sent:  # not a late probe's ack
            latencies.append(time.perf_counter() - sent.pop(seq))
            return True


def run_relay(node) -> None:
    cpu_start = None
    for event in node:
        if event["type"] != "INPUT":
            continue
        cpu_start = time.process_time() if cpu_start is None else cpu_start
        data = event["value"].to_numpy(zero_copy_only=True)
        node.send_output("blob", event["value"], {"seq": event["metadata"]["seq"], "sum": checksum(data)})
    _write_result("relay", {"cpu_s": time.process_time() - (cpu_start or time.process_time())})


def run_sink(node) -> None:
    import pyarrow as pa

    cpu_start = None
    for event in node:
        if event["type"] != "INPUT":
            continue
        cpu_start = time.process_time() if cpu_start is None else cpu_start
        node.send_output("ack", pa.array([event["value"].nbytes], pa.uint64()), {"seq": event["metadata"]["seq"]})
    _write_result("sink", {"cpu_s": time.process_time() - (cpu_start or time.process_time())})


def main(role: str) -> None:
    from dora import Node

    node = Node()
    if role == "source":
        run_source(
            node,
            int(os.environ["UMAD_DORA_FRAMES"]),
            int(os.environ["UMAD_DORA_SIZE"]),
            int(os.environ["UMAD_DORA_WINDOW"]),
        )
    elif role == "relay":
        run_relay(node)
    else:
        run_sink(node)


if __name__ == "__main__":
    main(sys.argv[1])
