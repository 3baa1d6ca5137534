"""Where a frame's time goes: the sums every replica keeps, their means, the launcher's table, and
the in-process pass `umad bench pipeline` measures the operators' own work with."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from umad_common import DEFAULT_GRAPH
from umad_common.benchmarks.pipeline import joined_inputs, stage_times, work_with_every_core_busy
from umad_common.dataflow.api.graph import load_graph
from umad_common.dataflow.api.messages import Message
from umad_common.dataflow.delivery.joiner import FrameJoiner
from umad_common.dataflow.delivery.stats import Stats
from umad_common.dataflow.launch.report import summary_table


def test_stats_turn_sums_into_means_per_frame_and_per_message():
    stats = Stats(frames_in=4, computed=2, cpu_s=0.3, process_cpu_s=0.5, messages_in=8, transport_s=0.016)
    stats.queue_s, stats.joined, stats.wait_s = 0.08, 4, 0.2
    means = stats.time_per_frame_ms()
    assert means["cpu_ms"] == pytest.approx(150.0)  # over the 2 frames computed, not the 4 markers too
    assert means["runtime_cpu_ms"] == pytest.approx(50.0)  # (0.5 - 0.3) s over 4 frames
    assert means["transport_ms"] == pytest.approx(2.0) and means["queue_ms"] == pytest.approx(10.0)
    assert means["wait_ms"] == pytest.approx(50.0)
    assert set(Stats().time_per_frame_ms().values()) == {None}  # nothing to divide by yet


def test_joiner_sums_the_wait_from_a_frames_first_input_to_its_last(monkeypatch):
    clock = iter([10.0, 10.25, 10.5])
    monkeypatch.setattr("umad_common.dataflow.delivery.joiner.time.monotonic", lambda: next(clock))
    joiner = FrameJoiner(["a", "b"], [])
    joiner.add("a", "p", Message("run", 0))  # first seen at 10.0
    joiner.add("b", "q", Message("run", 0))
    assert joiner.pop_ready({}) and joiner.joined == 1  # popped at 10.25
    assert joiner.wait_s == pytest.approx(0.25)


def test_summary_table_has_a_row_per_replica_and_dashes_for_what_is_unknown():
    row = {"frames_in": 3, "frames_out": 3, "errors": 0, "bad_messages": 0, "duplicates": 1}
    table = summary_table({"b.r0": {**row, "cpu_ms": 12.34, "wait_ms": None}, "a.r1": row})
    lines = table.splitlines()
    assert ["cpu", "rt", "wait", "queue", "bus"] <= lines[0].split()
    assert lines[1].startswith("a.r1") and lines[2].startswith("b.r0")
    assert "12.3" in lines[2] and "-" in lines[1].split()


def test_stage_times_weigh_each_replica_by_its_frames():
    stats = {
        "op.r0": {"frames_in": 3, "frames_out": 3, "cpu_ms": 10.0},
        "op.r1": {"frames_in": 1, "frames_out": 1, "cpu_ms": 30.0},
        "other.r0": {"frames_in": 9, "frames_out": 9, "cpu_ms": 99.0},
    }
    times = stage_times(stats, "op")
    assert times["cpu_ms"] == pytest.approx(15.0) and times["wait_ms"] is None


def test_default_graph_in_process_order_and_joined_inputs():
    graph = load_graph(DEFAULT_GRAPH)
    order = graph.topological_order()
    assert sorted(order) == sorted(op.id for op in graph.spec.operators)
    for op in graph.spec.operators:
        for port in op.inputs:
            for source in op.sources_of(port):
                assert all(order.index(p) < order.index(op.id) for p, _ in graph.producers(source))
    published = {
        (op, "map"): Message("r", 0, arrays={"map": np.zeros((2, 2), np.float32)})
        for op in ("diff_abs", "diff_ssim", "mnad")
    }
    frame = joined_inputs(graph, "fusion", "r", 0, 0, published)
    assert set(frame.many["maps"]) == {"diff_abs", "diff_ssim"}  # diff_*/map, not mnad's map


def test_a_replica_process_runs_numpy_blas_on_one_thread():
    """BLAS threads spin after each call: a replica keeps one (run_operator calls one_blas_thread first)."""
    probe = (
        "import json, numpy, threadpoolctl\n"
        "from umad_common.dataflow.process.replica import one_blas_thread\n"
        "blas = lambda: [p['num_threads'] for p in threadpoolctl.threadpool_info() if p['user_api'] == 'blas']\n"
        "before = blas()\n"
        "one_blas_thread()\n"
        "print(json.dumps([before, blas()]))\n"
    )
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2"}
    result = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    before, after = json.loads(result.stdout)
    assert before and max(before) == 2  # the probe sees numpy's BLAS with the threads the environment allows
    assert set(after) == {1}


def blob_chain(relay_params: dict) -> dict:
    return {
        "name": "chain",
        "operators": [
            {
                "id": "blobs",
                "uses": "umad_common.benchmarks.bus:BlobSource",
                "params": {"frames": 5, "size_bytes": 4096},
            },
            {
                "id": "relay",
                "uses": "umad_common.benchmarks.bus:Relay",
                "inputs": {"blob": "blobs/blob"},
                "params": relay_params,
            },
            {"id": "sink", "uses": "umad_common.benchmarks.bus:BlobSink", "inputs": {"blob": "relay/blob"}},
        ],
    }


def test_every_core_busy_pass_runs_the_whole_chain_in_each_process_and_names_a_failure():
    passes = work_with_every_core_busy(blob_chain({}), 2)
    assert len(passes) == 2
    for result in passes:
        assert set(result["cpu_ms"]) == {"blobs", "relay", "sink"} and result["fps"] > 0
    with pytest.raises(RuntimeError, match="no_such_param"):
        work_with_every_core_busy(blob_chain({"no_such_param": 1}), 2)
