"""Live mode's rule at a join, one replica in this process on an isolated Zenoh session with frames
fed to its queue: a frame whose last input is only late is still used, a frame whose input was
lost is passed over at its deadline once a newer one is processed, the newest is never given up,
a cheap operator catches up after a stall, and an operator slower than the camera takes only the
newest of its backlog."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from umad_common.dataflow.api.graph import validate_graph
from umad_common.dataflow.api.messages import Message, decode, encode
from umad_common.dataflow.process.runtime import OperatorRuntime, Received
from umad_common.dataflow.transport.bus import zenoh_config


def graph(log: str) -> dict:
    """A camera at 10 Hz and a join of its value with the value's double, which logs each frame."""
    join = {"id": "join", "uses": "tests.toy_ops:JoinSink", "inputs": {"a": "source/value", "b": "double/y"}}
    return {
        "name": "live_join",
        "operators": [
            {"id": "source", "uses": "tests.toy_ops:CounterSource", "params": {"pacing": "realtime", "rate_hz": 10}},
            {"id": "double", "uses": "tests.toy_ops:Scale", "inputs": {"x": "source/value"}},
            {**join, "params": {"log": log}},
        ],
    }


def a(seq: int) -> Received:
    return _received("a", "source", "value", seq)


def b(seq: int) -> Received:
    return _received("b", "double", "y", seq)


def _received(port: str, producer: str, output: str, seq: int) -> Received:
    msg = Message("run0", seq, seq * 100_000_000, producer, {}, {"x": np.full(4, float(seq), np.float32)})
    return Received(port, f"umad/live_join/{producer}/{output}", decode(encode(msg)), None, time.time())


@pytest.fixture
def join(tmp_path):
    session = zenoh.open(zenoh_config("peer"))  # no hub, no peers: publishing goes nowhere
    shutdown = threading.Event()
    join_graph = validate_graph(graph(str(tmp_path / "join.jsonl")))
    rt = OperatorRuntime(graph=join_graph, op_id="join", replica=0, session=session, shutdown=shutdown)
    rt.members.put("source", "r0")
    rt.members.put("double", "r0")
    yield rt
    shutdown.set()
    session.close()


def processed(rt: OperatorRuntime) -> list[int]:
    log = Path(rt.operator.params.log)
    return [json.loads(line)["seq"] for line in log.read_text().splitlines()] if log.exists() else []


def feed(rt: OperatorRuntime, messages: list[Received], until) -> None:
    """Queue `messages` at once (the loop then sees them together, as after a stall), run the
    transform loop until `until()` holds, and stop it."""
    for message in messages:
        rt.data_q.put(message)
    loop = threading.Thread(target=rt._transform_loop, daemon=True)
    loop.start()
    deadline = time.monotonic() + 30
    while not until() and time.monotonic() < deadline:
        time.sleep(0.01)
    rt.shutdown.set()
    loop.join(10)
    rt.shutdown.clear()
    assert until()


def test_live_join_uses_late_frames_passes_over_lost_ones_and_catches_up(join):
    assert join.live and join.frame_period_s == pytest.approx(0.1) and join.deadline_s() == 0.5
    feed(join, [a(0), a(1), b(1)], lambda: processed(join) == [1])  # 0's second input is late
    feed(join, [b(0)], lambda: processed(join) == [1, 0])  # and still used when it comes
    assert join.stats.superseded == 0

    started = time.monotonic()
    feed(join, [a(2), a(3), b(3)], lambda: join.stats.superseded == 1)  # 2's second input never comes
    assert time.monotonic() - started >= 0.5  # passed over at its deadline, not before
    feed(join, [b(2)], lambda: True)  # a late input of a passed-over frame is ignored
    assert not join.joiner.pending and processed(join) == [1, 0, 3]

    feed(join, [a(4)], lambda: True)
    time.sleep(0.6)
    feed(join, [b(4)], lambda: processed(join)[-1] == 4)  # the newest frame is never given up

    feed(join, [a(5), b(5), a(6), b(6), a(7), b(7)], lambda: processed(join)[-1] == 7)
    assert processed(join) == [1, 0, 3, 4, 5, 6, 7] and join.stats.superseded == 1  # cheap: the backlog caught up


def test_an_operator_slower_than_the_camera_takes_the_newest_of_its_backlog(join):
    join.processor.compute_s = 0.25  # as if each frame took 2.5 camera periods: more than the catch-up budget (2)
    feed(join, [a(0), b(0), a(1), b(1), a(2), b(2)], lambda: processed(join) == [2])
    assert join.stats.superseded == 2
    join.processor.compute_s = 0.08  # two frames fit in the catch-up budget
    feed(join, [a(3), b(3), a(4), b(4), a(5), b(5)], lambda: processed(join)[-1] == 5)
    assert processed(join) == [2, 4, 5] and join.stats.superseded == 3
