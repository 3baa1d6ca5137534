"""The runtime's per-frame work does not grow with the graph: which replica is a sink and which
producers a wildcard port waits for are worked out once, and again only when membership changes.
One replica runs in this process on an isolated Zenoh session; frames are fed to its queue."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest
import zenoh

from umad_common.dataflow.api.graph import validate_graph
from umad_common.dataflow.api.messages import Message, decode, encode
from umad_common.dataflow.process.runtime import OperatorRuntime, Received
from umad_common.dataflow.transport.bus import zenoh_config

GRAPH = {
    "name": "routes",
    "operators": [
        {"id": "source", "uses": "tests.toy_ops:CounterSource"},
        {"id": "double", "uses": "tests.toy_ops:Scale", "inputs": {"x": "source/value"}},
        {"id": "triple", "uses": "tests.toy_ops:Scale", "inputs": {"x": "source/value"}},
        {"id": "sink", "uses": "tests.toy_ops:JoinSink", "inputs": {"a": "source/value", "b": "*le/y"}},
    ],
}


class Counting:
    """Wraps a graph method and counts its calls."""

    def __init__(self, method):
        self.method, self.calls = method, 0

    def __call__(self, *args):
        self.calls += 1
        return self.method(*args)


def received(port: str, producer: str, output: str, seq: int) -> Received:
    msg = Message("run0", seq, seq, producer, {}, {"x": np.full(4, float(seq), np.float32)})
    return Received(port, f"umad/routes/{producer}/{output}", decode(encode(msg)), None, time.time())


@pytest.fixture
def runtime():
    session = zenoh.open(zenoh_config("peer"))  # no hub, no peers: publishing goes nowhere
    shutdown = threading.Event()
    rt = OperatorRuntime(graph=validate_graph(GRAPH), op_id="sink", replica=0, session=session, shutdown=shutdown)
    for op in ("source", "double", "triple"):
        rt.members.put(op, "r0")
    yield rt
    shutdown.set()
    session.close()


def graph_calls_for(rt: OperatorRuntime, frames: int) -> int:
    """Run the transform loop over `frames` joined frames; how often it asked the graph for sinks
    or producers."""
    sinks, producers = Counting(rt.graph.sinks), Counting(rt.graph.producers)
    rt.graph.sinks, rt.graph.producers = sinks, producers
    start = rt.stats.frames_in
    loop = threading.Thread(target=rt._transform_loop, daemon=True)
    loop.start()
    for seq in range(start, start + frames):
        rt.data_q.put(received("a", "source", "value", seq))
        rt.data_q.put(received("b", "double", "y", seq))
        rt.data_q.put(received("b", "triple", "y", seq))
    deadline = time.monotonic() + 60
    while rt.stats.frames_in < start + frames and time.monotonic() < deadline:
        time.sleep(0.01)
    rt.shutdown.set()
    loop.join(10)
    rt.shutdown.clear()
    assert rt.stats.frames_in == start + frames
    return sinks.calls + producers.calls


def test_graph_lookups_do_not_grow_with_frames(runtime):
    assert runtime.is_sink
    few = graph_calls_for(runtime, 3)
    many = graph_calls_for(runtime, 60)
    assert many <= few <= 3  # routes once per loop start: one producers lookup per live operator


def test_membership_change_recomputes_the_expected_producers(runtime):
    graph_calls_for(runtime, 2)
    assert runtime._routes()[0] == {"b": {"double", "triple"}}
    goodbye = msgpack.packb({"op": "triple", "replica": "r0"})
    runtime.members.delete("triple", "r0")  # its liveliness token went, after its goodbye below
    sample = SimpleNamespace(
        key_expr=runtime.keys.left("triple", "r0"), payload=SimpleNamespace(to_bytes=lambda: goodbye)
    )
    runtime.ctl_q.put(("left", sample))
    assert runtime.handle_service()
    assert runtime._routes()[0] == {"b": {"double"}}
