"""`umad bench pipeline`: the default graph end to end on a small generated benchmark, next to the
bound the machine sets.

Passes over the same frames. Every operator of the graph in this one process, frame by frame in
the graph's order, each `process` call timed in CPU seconds: the operators' own work per frame,
summed over the graph and divided by the cores, is the frames/s the machine could reach if the
dataflow cost nothing. That pass runs once before the graph and once after it, and the bound uses
their mean: a shared or virtual machine's speed drifts from one minute to the next
(docs/benchmarks.md), and a bound measured only before the graph moved the ratio by as much (both
passes are in the result, so the drift shows). Then the graph itself, as processes on a hub:
frames/s (frames over the source's first-send-to-last-ack time, start-up excluded), end-to-end
latency from the replayer's send to the accumulator's ack (p50/p99), their ratio to the bound, and
per operator where a frame's time went (the stats every replica publishes, see
`umad_common.dataflow.delivery.joiner.Stats`), so the operator to replicate or move to another
machine is visible. `operators_cpu_ms_per_frame` sets the operators' own CPU per frame in the graph
next to the in-process passes'.

The bound assumes a core's work costs the same whether or not the other cores are busy. Cores of
a virtual machine share caches, a memory bus or a physical core, so a last pass runs the in-process
pass in one process per core at once, started together: each operator's CPU per frame with every
core carrying the same work, and the bound that gives (`bound_fps_every_core_busy`). The graph's
ratio to that bound is the part of the gap the dataflow itself costs; the rest is the machine.

On a machine shared with other work the graph gets fewer cores than the bound assumes:
`cores_used` is the graph's CPU (every replica's, the hub's not counted) over its busy time, and
`work_share_of_graph_cpu` the part of that CPU which was the operators' own work (the rest is the
runtime and the bus), a figure other load moves much less than frames/s.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import yaml

from umad_common import DEFAULT_GRAPH
from umad_common.benchmarks.graphs import run_bench_graph
from umad_common.dataflow import Context, Frame, Operator, Source
from umad_common.dataflow.api.graph import Graph, validate_graph
from umad_common.dataflow.api.messages import Message
from umad_common.dataflow.api.operator import delivered
from umad_common.dataflow.process.allocator import keep_freed_memory
from umad_common.dataflow.process.replica import one_blas_thread

STAGE_FIELDS = ("cpu_ms", "runtime_cpu_ms", "wait_ms", "queue_ms", "transport_ms", "p50_ms")


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
    graph = validate_graph(graph_data)
    before = work_per_frame(graph)
    result = run_bench_graph(graph_data)
    after = work_per_frame(graph)
    cores = len(os.sched_getaffinity(0))
    busy = work_with_every_core_busy(graph_data, cores)
    work = {
        "cpu_ms": {op: (before["cpu_ms"][op] + after["cpu_ms"][op]) / 2 for op in before["cpu_ms"]},
        "fps": (before["fps"] + after["fps"]) / 2,
    }
    busy_cpu_ms = {op: sum(b["cpu_ms"][op] for b in busy) / len(busy) for op in work["cpu_ms"]}
    bound_fps = cores / (sum(work["cpu_ms"].values()) / 1e3)
    busy_bound_fps = cores / (sum(busy_cpu_ms.values()) / 1e3)
    in_graph = {op: stage_times(result["stats"], op) for op in work["cpu_ms"]}
    graph_cpu_s = sum(s.get("process_cpu_s", 0.0) for s in result["stats"].values())
    source = result["stats"][f"{graph.sources()[0]}.r0"]
    return {
        "frames": result["frames"],
        "cores": cores,
        "fps": result["fps"],
        "bound_fps": bound_fps,
        "bound_fps_passes": [cores / (sum(w["cpu_ms"].values()) / 1e3) for w in (before, after)],
        "fps_ratio_to_bound": result["fps"] / bound_fps,
        "bound_fps_every_core_busy": busy_bound_fps,
        "fps_ratio_to_every_core_busy_bound": result["fps"] / busy_bound_fps,
        "in_process_fps_every_core_busy": sum(b["fps"] for b in busy),
        "operators_cpu_ms_per_frame": {
            "alone": sum(work["cpu_ms"].values()),
            "every_core_busy": sum(busy_cpu_ms.values()),
            "graph": sum(times["cpu_ms"] or 0.0 for times in in_graph.values()),
        },
        "cores_used": graph_cpu_s / source["busy_s"],
        "work_share_of_graph_cpu": result["frames"] * sum(work["cpu_ms"].values()) / 1e3 / graph_cpu_s,
        "in_process_fps": work["fps"],
        "end_to_end_p50_ms": result["p50_ms"],
        "end_to_end_p99_ms": result["p99_ms"],
        "wall_s_with_startup": result["wall_s_with_startup"],
        "start_and_stop_s": result["start_and_stop_s"],
        "stages": {
            op: {"alone_cpu_ms": cpu_ms, "every_core_busy_cpu_ms": busy_cpu_ms[op], **in_graph[op]}
            for op, cpu_ms in work["cpu_ms"].items()
        },
    }


def work_per_frame(graph: Graph, ready: Callable[[], object] | None = None) -> dict:
    """Every operator of `graph` run in this process on the source's frames: CPU ms per frame of
    each one's own work (a source's: producing the frame), and the frames/s of the whole chain.
    BLAS runs on one thread and the allocator keeps freed memory, as in every replica, so the pass
    counts the same work. `ready` is called once every operator is built, before the first frame."""
    keep_freed_memory()
    with one_blas_thread():
        return _chain_in_this_process(graph, ready)


def _chain_in_this_process(graph: Graph, ready: Callable[[], object] | None) -> dict:
    ops: dict[str, Operator] = {
        spec.id: graph.classes[spec.id](spec.params, Context(spec.id, 0, graph.name, graph.base_dir))
        for spec in graph.spec.operators
    }
    if ready is not None:
        ready()
    order = graph.topological_order()
    source_id = graph.sources()[0]
    source = ops[source_id]
    assert isinstance(source, Source)
    cpu_s = dict.fromkeys(order, 0.0)
    count = 0
    start = time.perf_counter()
    frames = source.frames()
    while True:
        cpu_start = time.process_time()
        sf = next(frames, None)
        if sf is None:
            break
        cpu_s[source_id] += time.process_time() - cpu_start
        count += 1
        published = {
            (source_id, port): msg
            for port, msg in delivered(sf.outputs, sf.run, sf.seq, sf.stamp_ns, source_id).items()
        }
        for op_id in (op for op in order if op != source_id):
            frame = joined_inputs(graph, op_id, sf.run, sf.seq, sf.stamp_ns, published)
            cpu_start = time.process_time()
            outputs = ops[op_id].process(frame)
            cpu_s[op_id] += time.process_time() - cpu_start
            for port, msg in delivered(outputs, sf.run, sf.seq, sf.stamp_ns, op_id).items():
                published[(op_id, port)] = msg
    elapsed = time.perf_counter() - start
    for op in ops.values():
        op.close()
    return {"cpu_ms": {op: 1e3 * s / max(count, 1) for op, s in cpu_s.items()}, "fps": count / elapsed}


def work_with_every_core_busy(graph_data: dict, copies: int) -> list[dict]:
    """`work_per_frame` in `copies` processes at once, their frame loops started together (each
    builds its operators first); every process's result."""
    context = multiprocessing.get_context("spawn")
    barrier = context.Barrier(copies)
    results = context.Queue()
    processes = [context.Process(target=_pass_in_child, args=(graph_data, barrier, results)) for _ in range(copies)]
    for process in processes:
        process.start()
    passes: list[dict | str] = []
    while len(passes) < copies:
        try:
            passes.append(results.get(timeout=5.0))
        except queue.Empty:
            died = [p.exitcode for p in processes if p.exitcode not in (None, 0)]
            if died:
                barrier.abort()
                raise RuntimeError(
                    f"in-process pass with every core busy: a process died (exit codes {died})"
                ) from None
    for process in processes:
        process.join()
    errors = [p for p in passes if isinstance(p, str)]
    if errors:
        raise RuntimeError(f"in-process pass with every core busy failed: {errors}")
    return passes


def _pass_in_child(graph_data: dict, barrier, results) -> None:
    try:
        results.put(work_per_frame(validate_graph(graph_data), ready=barrier.wait))
    except BaseException as exc:  # reported to the parent, which would otherwise wait forever
        barrier.abort()
        results.put(f"{type(exc).__name__}: {exc}")


def joined_inputs(
    graph: Graph, op_id: str, run: str, seq: int, stamp_ns: int, published: dict[tuple[str, str], Message]
) -> Frame:
    """The frame the runtime would hand `op_id`: one message per single port, every matching
    producer's per `many` port."""
    spec = graph.op(op_id)
    frame = Frame(run, seq, stamp_ns)
    for port in graph.classes[op_id].inputs:
        if port.name not in spec.inputs:
            continue
        matches = {
            producer: published[(producer, output)]
            for source in spec.sources_of(port.name)
            for producer, output in graph.producers(source)
            if (producer, output) in published
        }
        if port.many:
            frame.many[port.name] = matches
        else:
            frame.inputs[port.name] = next(iter(matches.values()))
    return frame


def stage_times(stats: dict[str, dict], op_id: str) -> dict[str, float | None]:
    """One operator's per-frame times in the graph run, its replicas' means weighted by frames."""
    replicas = [s for name, s in stats.items() if name.rsplit(".", 1)[0] == op_id]
    times = {}
    for field in STAGE_FIELDS:
        weighted = [(s[field], max(s["frames_in"], s["frames_out"])) for s in replicas if s.get(field) is not None]
        frames = sum(n for _, n in weighted)
        times[field] = sum(v * n for v, n in weighted) / frames if frames else None
    return times
