"""`umad bench bus`: 1 MB frames through the hub between operator processes, against the same
function chain called in one process. Both sides encode and decode every message, so the ratio is
the price of the bus itself (transport, joining, acks), not of serialisation. The in-process chain
runs in a process of its own at the operators' CPU priority (the launcher lowers theirs), so on a
machine busy with other work both sides compete for the CPU on the same terms."""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
from pydantic import Field

from umad_common.allocator import keep_freed_memory
from umad_common.benchmarks.graphs import run_bench_graph
from umad_common.launcher import OPERATOR_NICENESS
from umad_common.messages import Message, decode, encode
from umad_common.operator import Frame, Input, Operator, Output, Source, SourceFrame
from umad_common.pacing import SourceParams


class BlobSource(Source):
    """Frames of `size_bytes` random bytes."""

    kind = "bench_blob"
    outputs = ("blob",)

    class Params(SourceParams):
        frames: int = Field(200, description="frames to send")
        size_bytes: int = Field(1 << 20, description="payload size per frame")

    def frames(self):
        blob = np.random.default_rng(0).integers(0, 255, self.params.size_bytes, dtype=np.uint8)
        for seq in range(self.params.frames):
            yield SourceFrame("bench", seq, seq, {"blob": Output({"data": blob})})


class Relay(Operator):
    """Passes the blob on, touching every byte (a checksum) as a real operator would read it."""

    kind = "bench_relay"
    inputs = (Input("blob"),)
    outputs = ("blob",)

    def process(self, frame):
        data = frame.inputs["blob"].arrays["data"]
        return {"blob": Output({"data": data}, {"sum": int(data[::4096].sum())})}


class BlobSink(Operator):
    kind = "bench_sink"
    inputs = (Input("blob"),)
    outputs = ("done",)

    def process(self, frame):
        return {"done": Output(meta={"bytes": sum(int(a.nbytes) for a in frame.inputs["blob"].arrays.values())})}


def in_process(frames: int, size_bytes: int) -> dict:
    """The same chain in a child process set up as a replica: niced as the launcher nices
    operators, its allocator keeping freed memory (`keep_freed_memory`)."""
    spawn = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=spawn, initializer=_as_a_replica) as pool:
        return pool.submit(chain_in_process, frames, size_bytes).result()


def _as_a_replica() -> None:
    os.nice(OPERATOR_NICENESS)
    keep_freed_memory()


def chain_in_process(frames: int, size_bytes: int) -> dict:
    """The same chain, one process: encode -> decode -> relay -> encode -> decode -> sink."""
    source, relay, sink = BlobSource({"frames": frames, "size_bytes": size_bytes}), Relay(), BlobSink()

    latencies = []
    start, cpu_start = time.perf_counter(), time.process_time()
    for sf in source.frames():
        t0 = time.perf_counter()
        msg = decode(encode(Message(sf.run, sf.seq, sf.stamp_ns, "source", {}, sf.outputs["blob"].arrays)))
        out = relay.process(Frame(sf.run, sf.seq, sf.stamp_ns, {"blob": msg}))["blob"]
        msg2 = decode(encode(Message(sf.run, sf.seq, sf.stamp_ns, "relay", out.meta, out.arrays)))
        sink.process(Frame(sf.run, sf.seq, sf.stamp_ns, {"blob": msg2}))
        latencies.append(time.perf_counter() - t0)
    elapsed, cpu_s = time.perf_counter() - start, time.process_time() - cpu_start
    lat = np.array(latencies) * 1e3
    return {
        "fps": frames / elapsed,
        "p50_ms": float(np.percentile(lat, 50)),
        "p99_ms": float(np.percentile(lat, 99)),
        "cpu_ms_per_frame": 1e3 * cpu_s / frames,
    }


def over_bus(frames: int, size_bytes: int, hub: str, window: int, shm_pool_mib: int | None = None) -> dict:
    """source -> relay -> sink as three processes on a hub; latency is send-to-ack at the source;
    CPU is the three processes' from their first frame on (the hub's not counted)."""
    result = run_bench_graph(
        {
            "name": "bench",
            "hub": hub,
            "shm_pool_mib": shm_pool_mib,
            "operators": [
                {
                    "id": "source",
                    "uses": f"{__name__}:BlobSource",
                    "params": {"frames": frames, "size_bytes": size_bytes, "window": window},
                },
                {"id": "relay", "uses": f"{__name__}:Relay", "inputs": {"blob": "source/blob"}},
                {"id": "sink", "uses": f"{__name__}:BlobSink", "inputs": {"blob": "relay/blob"}},
            ],
        }
    )
    cpu_s = sum(s.get("process_cpu_s", 0.0) for s in result["stats"].values())
    return {**result, "cpu_ms_per_frame": 1e3 * cpu_s / frames}


def bench_bus(
    frames: int = 300, size_bytes: int = 1 << 20, hub: str = "tcp/127.0.0.1:7449", shm_pool_mib: int | None = None
) -> dict:
    """`shm_pool_mib`: the graph's `shm_pool_mib` (None: Zenoh's default pool)."""
    local = in_process(frames, size_bytes)
    bus = over_bus(frames, size_bytes, hub, window=8, shm_pool_mib=shm_pool_mib)
    bus1 = over_bus(frames, size_bytes, hub, window=1, shm_pool_mib=shm_pool_mib)
    keep = ("fps", "p50_ms", "p99_ms", "cpu_ms_per_frame")
    return {
        "frames": frames,
        "frame_bytes": size_bytes,
        "shm_pool_mib": shm_pool_mib,
        "in_process": local,
        "bus_window_8": {k: bus[k] for k in keep},
        "bus_window_1": {k: bus1[k] for k in keep},
        "fps_ratio_bus_over_in_process": bus["fps"] / local["fps"],
        "p50_ratio_bus_window_1_over_in_process": bus1["p50_ms"] / local["p50_ms"],
        # two 1 MiB hops (source -> relay -> sink); the small ack back to the source is charged to them
        "p50_ms_added_per_hop_window_1": (bus1["p50_ms"] - local["p50_ms"]) / 2,
        "cpu_ratio_bus_window_8_over_in_process": bus["cpu_ms_per_frame"] / local["cpu_ms_per_frame"],
    }
