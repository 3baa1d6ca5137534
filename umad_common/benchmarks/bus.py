"""`umad bench bus`: 1 MB frames through the hub between operator processes, against the same
function chain called in one process. Both sides encode and decode every message, so the ratio is
the price of the bus itself (transport, joining, acks), not of serialisation. The in-process chain
runs in a process of its own at the operators' CPU priority (the launcher lowers theirs), so on a
machine busy with other work both sides compete for the CPU on the same terms.

The relay reads every byte of each frame (`blobs.checksum`), as a real operator reads its input.

The bus runs four times at window 8: as graphs run on x86 (payloads through the publishers'
shared-memory rings, Zenoh carrying references: `planes/ring.py`; replicas linked directly, not
through the hub), with `shared_payloads: zenoh_shm` (payloads in Zenoh's shared memory, as on other
CPUs: `planes/zenoh_shm.py`), with `shared_payloads: false` (every payload through Zenoh as it is), and
with `direct_links: false` (every message through the hub). Their ratios are what the rings, Zenoh's
shared memory and the direct links buy. `--against dora`: the same relay as a dora-rs dataflow
(`dora_relay.py`), run right after the bus.

What securing the hub costs: the bus with every message through the hub and every payload through
its sockets, neither in the payload rings nor in Zenoh's shared memory (as for a worker on another
host, whose bytes all cross the link and so are all encrypted), over plain TCP, over mutual TLS (`tls:`: every process
presents a certificate of the graph's CA), and over mutual TLS with the hub's access control
(`security:`, each certificate's role enforced by Zenoh), side by side in one run.

Between in-process and the bus, the floor of a dataflow that moves its payloads through Zenoh: the
same three processes doing the same work on plain Zenoh sessions (`bare_zenoh`: a publisher, a
subscriber read on the main thread, the sink's acks straight to the source), without the runtime's
joins, ordering, cache, stats or membership. The bus through Zenoh against bare Zenoh is what the
runtime costs (the two measured in alternating rounds, `runtime_against_bare_zenoh`); bare Zenoh
against in-process is what that transport costs, whatever runs on it."""

from __future__ import annotations

import multiprocessing
import os
import queue
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import msgpack
import numpy as np
import zenoh
from pydantic import Field

from umad_common.benchmarks.blobs import checksum
from umad_common.benchmarks.graphs import run_bench_graph
from umad_common.dataflow import Frame, Input, Operator, Output, Source, SourceFrame, SourceParams
from umad_common.dataflow.api.messages import Message, decode, encode
from umad_common.dataflow.launch.replicas import OPERATOR_NICENESS
from umad_common.dataflow.process.allocator import keep_freed_memory
from umad_common.dataflow.transport.bus import open_client, open_hub
from umad_common.dataflow.transport.certificates import HUB, bundle_paths, make_certificates, operator_identity


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
    """Passes the blob on, reading every byte (`checksum`) as a real operator would read it."""

    kind = "bench_relay"
    inputs = (Input("blob"),)
    outputs = ("blob",)

    def process(self, frame):
        data = frame.inputs["blob"].arrays["data"]
        return {"blob": Output({"data": data}, {"sum": checksum(data)})}


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


CHAIN = ("source", "relay", "sink")


def over_bus(
    frames: int,
    size_bytes: int,
    hub: str,
    window: int,
    shm_pool_mib: int | None = None,
    shared_payloads: bool = True,
    direct_links: bool = True,
    security: dict | None = None,
) -> dict:
    """source -> relay -> sink as three processes on a hub; latency is send-to-ack at the source;
    CPU is the three processes' from their first frame on (the hub's not counted). `security`: the
    graph's `tls:` and `security:` blocks (`secured`)."""
    result = run_bench_graph(
        {
            "name": "bench",
            "hub": hub,
            "shm_pool_mib": shm_pool_mib,
            "shared_payloads": shared_payloads,
            "direct_links": direct_links,
            **(security or {}),
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
    hub_cpu_ms = 1e3 * result["hub_cpu_s"] / frames if result["hub_cpu_s"] is not None else float("nan")
    return {**result, "cpu_ms_per_frame": 1e3 * cpu_s / frames, "hub_cpu_ms_per_frame": hub_cpu_ms}


BARE_READY_TIMEOUT_S = 30.0
KEPT = ("fps", "p50_ms", "p99_ms", "cpu_ms_per_frame")  # the figures a side of the bench reports


def bare_zenoh(frames: int, size_bytes: int, hub: str, window: int) -> dict:
    """source -> relay -> sink as three processes on plain Zenoh sessions through a hub opened here;
    latency is send-to-ack at the source; CPU is the three processes' over their frames."""
    spawn = multiprocessing.get_context("spawn")
    hub_session = open_hub(hub)
    events, go = spawn.Queue(), spawn.Event()
    stages = [
        spawn.Process(target=_bare_stage, args=(name, frames, size_bytes, hub, window, events, go), daemon=True)
        for name in ("sink", "relay", "source")
    ]
    try:
        for stage in stages:
            stage.start()
        _bare_events(events, "ready", BARE_READY_TIMEOUT_S)  # each publisher reaches its subscriber
        go.set()
        measured = _bare_events(events, "result", BARE_READY_TIMEOUT_S + frames)
    finally:
        for stage in stages:
            if stage.pid is not None:
                stage.join(5)
            if stage.is_alive():
                stage.kill()
        hub_session.close()
    source = measured["source"]
    lat = np.array(source["latencies_s"]) * 1e3
    cpu_s = sum(values["cpu_s"] for values in measured.values())
    return {
        "fps": frames / source["busy_s"],
        "p50_ms": float(np.percentile(lat, 50)),
        "p99_ms": float(np.percentile(lat, 99)),
        "cpu_ms_per_frame": 1e3 * cpu_s / frames,
    }


def _bare_events(events, kind: str, timeout_s: float) -> dict:
    """The `kind` event of each of the three stages, {stage: value}; a stage's error is raised here."""
    got: dict = {}
    while len(got) < 3:
        try:
            name, event, value = events.get(timeout=timeout_s)
        except queue.Empty:
            missing = sorted({"source", "relay", "sink"} - set(got))
            raise RuntimeError(f"bare Zenoh chain: no {kind} from {missing} within {timeout_s:.0f} s") from None
        if event == "error":
            raise RuntimeError(f"bare Zenoh chain, {name}: {value}")
        got[name] = value
    return got


def _bare_stage(name, frames, size_bytes, hub, window, events, go) -> None:
    """One process of the bare chain, set up as a replica (niced, keeping freed memory)."""
    _as_a_replica()
    session = open_client(hub)
    try:
        if name == "source":
            result = _bare_source(session, frames, size_bytes, window, events, go)
        else:
            result = _bare_consumer(session, name, frames, events)
        events.put((name, "result", result))
    except Exception as exc:
        events.put((name, "error", f"{type(exc).__name__}: {exc}"))
    finally:
        session.close()


def _bare_consumer(session, name: str, frames: int, events) -> dict:
    """The relay (decode, checksum, encode, put) or the sink (decode, ack to the source)."""
    publisher = session.declare_publisher(f"bench/bare/{name}", congestion_control=zenoh.CongestionControl.BLOCK)
    subscriber = session.declare_subscriber(
        "bench/bare/source" if name == "relay" else "bench/bare/relay", zenoh.handlers.FifoChannel(64)
    )
    _wait_for_subscriber(publisher)
    events.put((name, "ready", None))
    cpu_start = None
    for _ in range(frames):
        payload = subscriber.recv().payload.to_bytes()
        cpu_start = time.process_time() if cpu_start is None else cpu_start
        msg = decode(payload)
        if name == "relay":
            out = Relay().process(Frame(msg.run, msg.seq, msg.stamp_ns, {"blob": msg}))["blob"]
            publisher.put(encode(Message(msg.run, msg.seq, msg.stamp_ns, "relay", out.meta, out.arrays)))
        else:
            BlobSink().process(Frame(msg.run, msg.seq, msg.stamp_ns, {"blob": msg}))
            publisher.put(msgpack.packb(msg.seq))
    return {"cpu_s": time.process_time() - cpu_start}


def _bare_source(session, frames: int, size_bytes: int, window: int, events, go) -> dict:
    """Publish `frames` blobs once every stage is ready, at most `window` not yet acked by the sink."""
    slots, sent, latencies = threading.Semaphore(window), {}, []
    done = threading.Event()

    def on_ack(sample: zenoh.Sample) -> None:
        latencies.append(time.perf_counter() - sent[msgpack.unpackb(sample.payload.to_bytes())])
        slots.release()
        if len(latencies) == frames:
            done.set()

    subscriber = session.declare_subscriber("bench/bare/sink", on_ack)
    publisher = session.declare_publisher("bench/bare/source", congestion_control=zenoh.CongestionControl.BLOCK)
    _wait_for_subscriber(publisher)
    events.put(("source", "ready", None))
    go.wait(BARE_READY_TIMEOUT_S)
    source = BlobSource({"frames": frames, "size_bytes": size_bytes})
    start, cpu_start = time.perf_counter(), time.process_time()
    for sf in source.frames():
        slots.acquire()
        sent[sf.seq] = time.perf_counter()
        publisher.put(encode(Message(sf.run, sf.seq, sf.stamp_ns, "source", {}, sf.outputs["blob"].arrays)))
    if not done.wait(BARE_READY_TIMEOUT_S):
        raise RuntimeError(f"bare Zenoh chain: {len(latencies)} of {frames} frames acked")
    busy_s, cpu_s = time.perf_counter() - start, time.process_time() - cpu_start
    subscriber.undeclare()
    return {"busy_s": busy_s, "cpu_s": cpu_s, "latencies_s": latencies}


def _wait_for_subscriber(publisher) -> None:
    """Until the hub knows a subscriber for `publisher` (a put before that reaches nobody)."""
    deadline = time.monotonic() + BARE_READY_TIMEOUT_S
    while not publisher.matching_status.matching:
        if time.monotonic() > deadline:
            raise RuntimeError(f"bare Zenoh chain: nobody subscribed to {publisher.key_expr}")
        time.sleep(0.01)


def secured(folder: Path, access_control: bool) -> dict:
    """The bench graph's `tls:` block, certificates made in `folder`, and with `access_control` its
    `security:` block giving each operator its own role."""
    make_certificates(folder / "certs", folder / "ca", "bench", list(CHAIN), ["localhost", "127.0.0.1"])
    root_ca, cert, key = bundle_paths(folder / "certs", HUB)
    blocks: dict = {
        "tls": {"root_ca": str(root_ca), "cert": str(cert), "key": str(key), "certs": str(folder / "certs")}
    }
    if access_control:
        roles = {HUB: "launcher"} | {operator_identity(op): f"operator:{op}" for op in CHAIN}
        blocks["security"] = {"roles": roles}
    return blocks


SECURITY_MODES = ("tcp", "mtls", "mtls_acl")
SOCKETS_ONLY_POOL_MIB = 1  # a Zenoh shared-memory pool smaller than a frame: every payload crosses the sockets


def bench_security(frames: int, size_bytes: int, hub: str, window: int = 8, rounds: int = 3) -> dict:
    """The bus through the hub over plain TCP, mutual TLS, and mutual TLS with access control, in
    `rounds` rounds, each running the three in a rotated order, so load from elsewhere falls on
    each of them alike; per mode the median over rounds, and each round's ratios. The hub, which
    decrypts, checks and encrypts every message, is measured too (`hub_cpu_ms_per_frame`: its CPU
    over its life, start-up included, per frame)."""
    tls_hub = "tls/" + hub.partition("/")[2]
    through_sockets = {"shared_payloads": False, "direct_links": False, "shm_pool_mib": SOCKETS_ONLY_POOL_MIB}
    runs: dict[str, list[dict]] = {mode: [] for mode in SECURITY_MODES}
    with tempfile.TemporaryDirectory(prefix="umad-bench-certs-") as scratch:
        settings = {
            "tcp": (hub, None),
            "mtls": (tls_hub, secured(Path(scratch), access_control=False)),
            "mtls_acl": (tls_hub, secured(Path(scratch), access_control=True)),
        }
        for round_index in range(rounds):
            turn = round_index % len(SECURITY_MODES)
            for mode in SECURITY_MODES[turn:] + SECURITY_MODES[:turn]:
                endpoint, security = settings[mode]
                runs[mode].append(over_bus(frames, size_bytes, endpoint, window, **through_sockets, security=security))
    median = {mode: medians(done, (*KEPT, "hub_cpu_ms_per_frame")) for mode, done in runs.items()}

    def per_round(mode: str, field: str) -> list[float]:
        return [a[field] / b[field] for a, b in zip(runs[mode], runs["tcp"], strict=True)]

    return {
        "rounds": rounds,
        **{f"through_sockets_{mode}": values for mode, values in median.items()},
        "fps_ratio_mtls_over_tcp": median["mtls"]["fps"] / median["tcp"]["fps"],
        "fps_ratio_mtls_acl_over_tcp": median["mtls_acl"]["fps"] / median["tcp"]["fps"],
        "fps_ratio_mtls_acl_over_mtls": median["mtls_acl"]["fps"] / median["mtls"]["fps"],
        "p50_ratio_mtls_acl_over_tcp": median["mtls_acl"]["p50_ms"] / median["tcp"]["p50_ms"],
        "cpu_ratio_mtls_acl_over_tcp": median["mtls_acl"]["cpu_ms_per_frame"] / median["tcp"]["cpu_ms_per_frame"],
        "hub_cpu_ratio_mtls_over_tcp": median["mtls"]["hub_cpu_ms_per_frame"] / median["tcp"]["hub_cpu_ms_per_frame"],
        "hub_cpu_ratio_mtls_acl_over_tcp": median["mtls_acl"]["hub_cpu_ms_per_frame"]
        / median["tcp"]["hub_cpu_ms_per_frame"],
        "fps_ratio_mtls_over_tcp_per_round": per_round("mtls", "fps"),
        "fps_ratio_mtls_acl_over_tcp_per_round": per_round("mtls_acl", "fps"),
        "cpu_ratio_mtls_acl_over_tcp_per_round": per_round("mtls_acl", "cpu_ms_per_frame"),
    }


def runtime_against_bare_zenoh(
    frames: int, size_bytes: int, hub: str, shm_pool_mib: int | None, rounds: int = 3
) -> tuple[dict, dict, list[float]]:
    """Bare Zenoh and the bus through Zenoh (`shared_payloads: false`) at window 8, in `rounds` rounds
    whose order alternates, so load from elsewhere and the machine's drift fall on both alike: per
    side the median over rounds of each figure, and each round's frames/s ratio (bus over bare)."""
    runs: dict[str, list[dict]] = {"bare": [], "bus": []}
    for round_index in range(rounds):
        for side in ("bare", "bus") if round_index % 2 == 0 else ("bus", "bare"):
            if side == "bare":
                runs[side].append(bare_zenoh(frames, size_bytes, hub, window=8))
            else:
                runs[side].append(
                    over_bus(frames, size_bytes, hub, window=8, shm_pool_mib=shm_pool_mib, shared_payloads=False)
                )
    per_round = [bus["fps"] / bare["fps"] for bus, bare in zip(runs["bus"], runs["bare"], strict=True)]
    return medians(runs["bare"], KEPT), medians(runs["bus"], KEPT), per_round


def medians(runs: list[dict], figures: tuple[str, ...]) -> dict[str, float]:
    """Each of `figures` as its median over `runs` (one round's result each)."""
    return {figure: float(np.median([run[figure] for run in runs])) for figure in figures}


def bench_bus(
    frames: int = 2000,
    size_bytes: int = 1 << 20,
    hub: str = "tcp/127.0.0.1:7449",
    shm_pool_mib: int | None = None,
    security_only: bool = False,
    against: str | None = None,
) -> dict:
    """`shm_pool_mib`: the graph's `shm_pool_mib` (None: Zenoh's default pool). `security_only`: only
    what securing the hub costs (`bench_security`). `against="dora"`: also the relay as a dora-rs
    dataflow (`dora_relay.py`), right after the bus, and their ratios."""
    security = bench_security(frames, size_bytes, hub)
    if security_only:
        return {"frames": frames, "frame_bytes": size_bytes, "security": security}
    local = in_process(frames, size_bytes)
    bare, through_zenoh, runtime_share = runtime_against_bare_zenoh(frames, size_bytes, hub, shm_pool_mib)
    bus = over_bus(frames, size_bytes, hub, window=8, shm_pool_mib=shm_pool_mib)
    peer = against_dora(frames, size_bytes, bus) if against == "dora" else {}
    zenoh_shm = over_bus(frames, size_bytes, hub, window=8, shm_pool_mib=shm_pool_mib, shared_payloads="zenoh_shm")
    through_hub = over_bus(frames, size_bytes, hub, window=8, shm_pool_mib=shm_pool_mib, direct_links=False)
    bus1 = over_bus(frames, size_bytes, hub, window=1, shm_pool_mib=shm_pool_mib)
    return {
        "frames": frames,
        "frame_bytes": size_bytes,
        "shm_pool_mib": shm_pool_mib,
        "in_process": local,
        "bare_zenoh_window_8": bare,
        "bus_window_8": {k: bus[k] for k in KEPT},
        **peer,
        "bus_window_8_zenoh_shm": {k: zenoh_shm[k] for k in KEPT},
        "bus_window_8_through_zenoh": {k: through_zenoh[k] for k in KEPT},
        "bus_window_8_through_hub": {k: through_hub[k] for k in KEPT},
        "bus_window_1": {k: bus1[k] for k in KEPT},
        "fps_ratio_bus_over_in_process": bus["fps"] / local["fps"],
        "fps_ratio_bus_over_bus_through_zenoh": bus["fps"] / through_zenoh["fps"],
        "fps_ratio_bus_over_bus_zenoh_shm": bus["fps"] / zenoh_shm["fps"],
        "fps_ratio_bus_over_bus_through_hub": bus["fps"] / through_hub["fps"],
        "fps_ratio_bare_zenoh_over_in_process": bare["fps"] / local["fps"],
        "fps_ratio_bus_through_zenoh_over_bare_zenoh": through_zenoh["fps"] / bare["fps"],
        "fps_ratio_bus_through_zenoh_over_bare_zenoh_per_round": runtime_share,
        "p50_ratio_bus_window_1_over_in_process": bus1["p50_ms"] / local["p50_ms"],
        # two 1 MiB hops (source -> relay -> sink); the small ack back to the source is charged to them
        "p50_ms_added_per_hop_window_1": (bus1["p50_ms"] - local["p50_ms"]) / 2,
        "cpu_ratio_bus_window_8_over_in_process": bus["cpu_ms_per_frame"] / local["cpu_ms_per_frame"],
        "security": security,
    }


def against_dora(frames: int, size_bytes: int, bus: dict) -> dict:
    """The relay as a dora-rs dataflow at window 8, lossless and with blocking publishers
    (`dora_relay.py`), and the bus's ratios to each; without dora-rs one line saying so, and
    nothing else."""
    from umad_common.benchmarks.dora_relay import dora_missing, over_dora

    missing = dora_missing()
    if missing:
        print(missing, flush=True)
        return {"dora_window_8": missing}
    keep = (*KEPT, "daemon_cpu_ms_per_frame", "lost_frames")
    lossless = over_dora(frames, size_bytes, window=8)
    blocking = over_dora(frames, size_bytes, window=8, lossless=False)
    return {
        "dora_window_8": {k: lossless[k] for k in keep},
        "dora_window_8_blocking_publishers": {k: blocking[k] for k in keep},
        "fps_ratio_bus_over_dora": bus["fps"] / lossless["fps"],
        "cpu_ratio_bus_over_dora": bus["cpu_ms_per_frame"] / lossless["cpu_ms_per_frame"],
        "fps_ratio_bus_over_dora_blocking_publishers": bus["fps"] / blocking["fps"],
        "cpu_ratio_bus_over_dora_blocking_publishers": bus["cpu_ms_per_frame"] / blocking["cpu_ms_per_frame"],
    }
