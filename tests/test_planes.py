"""Every payload plane through the same cases (`transport/planes`): a large array there and back,
a small payload inline, what the message carries, a payload that is gone; the choice of plane, and
graphs launched on each plane. What one plane does alone is in test_planes_<name>.py."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
import zenoh

from tests.conftest import run_umad
from tests.test_runtime_e2e import assert_exactly_once, toy_graph
from umad_common.dataflow.api.graph import GraphSpec
from umad_common.dataflow.api.messages import Message, MessageError, decode, encode
from umad_common.dataflow.record.mcap_log import read_log
from umad_common.dataflow.transport import planes
from umad_common.dataflow.transport.bus import open_client, open_hub
from umad_common.dataflow.transport.planes import (
    INLINE_BELOW,
    PLANES,
    PayloadPlane,
    on_this_host,
    open_plane,
    payload_plane,
    plane_class,
)
from umad_common.dataflow.transport.planes import ring as ring_plane
from umad_common.dataflow.transport.planes.ring import KEPT_FOR_FETCH, RING_DIR, SWEPT_BY_LAUNCHER, is_reference

PREFIX = "umad/t/_payload/source"
EVERY_PLANE = [
    pytest.param(
        name,
        marks=pytest.mark.skipif(
            name == "ring" and not ring_plane.ring_is_correct_here(), reason="the ring needs x86's memory order"
        ),
    )
    for name in PLANES
]


def payload(size: int, fill: int = 0) -> bytes:
    return encode(Message("run", fill, 0, "test", {}, {"x": np.full(size, fill, np.uint8)}))


def on_the_wire(put: bytes | zenoh.ZBytes) -> bytes:
    """What a subscriber receives for what `put` returned (`sample.payload.to_bytes()`)."""
    return put if isinstance(put, bytes) else put.to_bytes()


@pytest.fixture
def host(tmp_path, monkeypatch):
    """Planes on a "host" of their own: `host("a")` opens planes whose rings live in tmp_path/a."""
    monkeypatch.delenv(SWEPT_BY_LAUNCHER, raising=False)
    opened = []

    def open_on(name: str, plane: str = "inline") -> planes.Planes:
        (tmp_path / name).mkdir(exist_ok=True)
        monkeypatch.setattr(ring_plane, "RING_DIR", tmp_path / name)
        opened.append(open_plane(plane, PREFIX, pool_mib=16))
        return opened[-1]

    yield open_on
    for plane in opened:
        plane.close()


@pytest.fixture
def sessions(hub_endpoint):
    hub = open_hub(hub_endpoint)
    publisher, subscriber = open_client(hub_endpoint), open_client(hub_endpoint)
    yield publisher, subscriber
    for session in (publisher, subscriber, hub):
        session.close()


def test_every_registered_plane_is_a_payload_plane_named_as_registered():
    for name in PLANES:
        plane = plane_class(name)(PREFIX, None, publishing=False)
        assert isinstance(plane, PayloadPlane) and plane.name == name
    assert isinstance(open_plane(), PayloadPlane)


@pytest.mark.parametrize("name", EVERY_PLANE)
def test_a_large_array_goes_through_zenoh_and_comes_back_byte_for_byte(name, host, sessions):
    publisher_session, subscriber_session = sessions
    publisher, subscriber = host("a", name), host("a")
    received: list[bytes] = []
    listener = subscriber_session.declare_subscriber("umad/t/x", lambda s: received.append(s.payload.to_bytes()))
    put = publisher_session.declare_publisher("umad/t/x", congestion_control=zenoh.CongestionControl.BLOCK)
    deadline = time.monotonic() + 10
    while not put.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.01)
    large = payload(1 << 20, 7)
    put.put(publisher.put(large))
    deadline = time.monotonic() + 10
    while not received and time.monotonic() < deadline:
        time.sleep(0.01)
    taken = subscriber.take(received[0])
    assert taken == large and (decode(taken).arrays["x"] == 7).all()
    listener.undeclare()


@pytest.mark.parametrize("name", EVERY_PLANE)
def test_a_small_payload_travels_inline(name, host):
    publisher, subscriber = host("a", name), host("a")
    small = payload(INLINE_BELOW // 2, 1)
    assert publisher.put(small) == small and subscriber.take(small) == small


# what the message carries for a large payload: the payload itself, a reference (a few dozen bytes,
# never taken for a message) or a buffer of Zenoh's shared memory holding it
CARRIED = {
    "inline": lambda put, large: put == large,
    "ring": lambda put, large: isinstance(put, bytes) and is_reference(put) and len(put) < 100,
    "zenoh_shm": lambda put, large: isinstance(put, zenoh.ZBytes) and put.to_bytes() == large,
}


@pytest.mark.parametrize("name", EVERY_PLANE)
def test_what_the_message_carries_for_a_large_payload(name, host):
    publisher, subscriber = host("a", name), host("a")
    large = payload(1 << 20, 5)
    put = publisher.put(large)
    assert CARRIED[name](put, large)
    raw = on_the_wire(put)
    assert subscriber.take(raw) == large
    if raw != large:
        with pytest.raises(MessageError, match="not valid msgpack"):  # a description is never a message
            decode(raw)


def taken_or_fetched(plane: planes.Planes, session: zenoh.Session, raw: bytes, wait_s: float = 0.0) -> bytes | None:
    """What a subscriber ends up with: the payload taken, else fetched from its publisher (for up to
    `wait_s`: a queryable's declaration reaches the hub after a while)."""
    deadline = time.monotonic() + wait_s
    while (got := plane.take(raw)) is None and (got := plane.fetch(session, PREFIX, raw)) is None:
        if time.monotonic() >= deadline:
            return None
        time.sleep(0.05)
    return got


# whether a payload its publisher has moved on from is gone for a subscriber that cannot reach the
# plane's memory: a ring's publisher keeps only its last payloads to serve; the other planes' messages
# carry the payload's bytes to another host
GONE_ONCE_PUBLISHER_MOVED_ON = {"inline": False, "ring": True, "zenoh_shm": False}


@pytest.mark.parametrize("name", EVERY_PLANE)
def test_a_subscriber_on_another_host_gets_the_payload_until_it_is_gone(name, host, sessions):
    publisher_session, subscriber_session = sessions
    publisher = host("a", name)
    declared = publisher.declare(publisher_session)
    elsewhere = host("b")  # another host: its own /dev/shm, where the publisher's memory is not
    large = payload(1 << 20, 3)
    raw = on_the_wire(publisher.put(large))
    assert taken_or_fetched(elsewhere, subscriber_session, raw, wait_s=10) == large
    for fill in range(KEPT_FOR_FETCH + 36):  # the publisher moves on
        publisher.put(payload(INLINE_BELOW, fill % 256))
    late = taken_or_fetched(elsewhere, subscriber_session, raw)
    assert late is None if GONE_ONCE_PUBLISHER_MOVED_ON[name] else late == large
    for each in declared:
        each.undeclare()


@pytest.mark.parametrize("name", EVERY_PLANE)
def test_a_payload_its_publisher_closed_on_is_gone_or_carried_as_today(name, host, sessions):
    """A publisher that closed its plane (a replica on its own, `umad op run`, unlinks its ring): a
    subscriber that maps the ring only now finds nothing, and no publisher answers a fetch."""
    _, subscriber_session = sessions
    publisher = host("a", name)
    large = payload(1 << 20, 4)
    raw = on_the_wire(publisher.put(large))
    publisher.close()
    late = taken_or_fetched(host("a"), subscriber_session, raw)
    assert late is None if GONE_ONCE_PUBLISHER_MOVED_ON[name] else late == large


def test_a_subscriber_takes_what_any_plane_put_whatever_plane_it_publishes_with(host):
    """A worker on another host publishes inline yet receives ring references and Zenoh's buffers
    from the hub's host; the recorder publishes nothing and takes them all."""
    large = payload(1 << 20, 9)
    put = {name: on_the_wire(host("a", name).put(large)) for name in PLANES}
    for mine in PLANES:
        subscriber = host("a", mine)
        assert {name: subscriber.take(raw) for name, raw in put.items()} == dict.fromkeys(PLANES, large)


def test_the_plane_a_graph_chooses_on_x86():
    assert payload_plane(True, "x86_64") == "ring"
    assert payload_plane("zenoh_shm", "x86_64") == "zenoh_shm"
    assert payload_plane(False, "x86_64") == "inline"
    assert {name: payload_plane(name, "x86_64") for name in PLANES} == {name: name for name in PLANES}


@pytest.mark.parametrize("machine", ["aarch64", "arm64", "riscv64", "ppc64le"])
def test_on_a_cpu_without_x86_memory_order_the_ring_gives_way_to_zenohs_shared_memory(monkeypatch, machine, caplog):
    monkeypatch.setattr("platform.machine", lambda: machine)
    with caplog.at_level(logging.INFO, "umad.payloads"):
        assert payload_plane(True) == "zenoh_shm"
    assert caplog.messages == [
        f"payload rings need x86's memory order and this CPU is {machine}: "
        "large payloads go through Zenoh's shared memory"
    ]
    assert payload_plane("ring") == "zenoh_shm"
    assert payload_plane("zenoh_shm") == "zenoh_shm" and payload_plane(False) == "inline"


def test_a_graph_names_a_plane_by_true_false_or_its_registered_name():
    for setting in (True, False, *PLANES):
        assert GraphSpec(operators=[], shared_payloads=setting).shared_payloads == setting
    with pytest.raises(ValueError, match="shared_payloads"):
        GraphSpec(operators=[], shared_payloads="carrier_pigeon")


def test_a_replica_whose_hub_is_on_another_host_publishes_inline():
    assert on_this_host("tcp/127.0.0.1:7447") and on_this_host("tls/localhost:7447")
    assert not on_this_host("tcp/192.0.2.1:7447")  # TEST-NET-1: never an address of this machine


def large_toy_graph(tmp_path: Path, hub: str, shared_payloads: bool | str = True, **kw) -> Path:
    """The toy graph with 400 KB frames: every frame message goes through the plane `shared_payloads`
    chooses (true: the rings on x86)."""
    path = toy_graph(tmp_path, hub, **kw)
    data = yaml.safe_load(path.read_text())
    data["operators"][0]["params"]["size"] = 100_000
    data["shared_payloads"] = shared_payloads
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_a_graph_on_each_plane_delivers_every_frame_once_and_records_the_same_bytes(tmp_path, hub_endpoint):
    logs = {}
    for setting in (True, "zenoh_shm", False):
        folder = tmp_path / str(setting)
        folder.mkdir()
        graph = large_toy_graph(folder, hub_endpoint, shared_payloads=setting, frames=12)
        logs[setting] = folder / "run.mcap"
        rings_before = set(RING_DIR.glob("umad-*.ring"))
        result = run_umad("launch", str(graph), "--record", str(logs[setting]), timeout=120)
        assert result.returncode == 0, result.stdout
        assert_exactly_once(folder, 12)
        if payload_plane(setting) != "ring":
            assert set(RING_DIR.glob("umad-*.ring")) <= rings_before  # no replica made a ring

    def source_payloads(path):
        return sorted(r.data for r in read_log(path) if r.topic.startswith("umad/toy/source/"))

    def sink_arrays(path):  # the sink's meta names its log file, which differs
        sink = (decode(r.data) for r in read_log(path) if r.topic.startswith("umad/toy/sink/"))
        return sorted((m.run, m.seq, m.arrays["x"].tobytes()) for m in sink if "x" in m.arrays)

    assert source_payloads(logs[True]) == source_payloads(logs["zenoh_shm"]) == source_payloads(logs[False])
    assert sink_arrays(logs[True]) == sink_arrays(logs["zenoh_shm"]) == sink_arrays(logs[False]) != []
