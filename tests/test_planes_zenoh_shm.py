"""Plane `zenoh_shm`: payloads in a publisher's pool of Zenoh's shared memory, Zenoh handing the
buffer to subscribers on this host. What every plane does alike is in test_planes.py."""

from __future__ import annotations

import time

import zenoh

from tests.test_planes import payload
from umad_common.dataflow.transport.bus import open_client, open_hub
from umad_common.dataflow.transport.planes.zenoh_shm import ZenohShmPayloads


def test_a_payload_in_zenohs_shared_memory_reaches_a_subscriber_whole_and_a_full_pool_sends_it_as_it_is(
    hub_endpoint,
):
    hub = open_hub(hub_endpoint)
    publisher, subscriber = open_client(hub_endpoint), open_client(hub_endpoint)
    received = []
    try:
        listener = subscriber.declare_subscriber("umad/t/x", lambda sample: received.append(sample.payload.to_bytes()))
        put = publisher.declare_publisher(  # as the runtime's: a busy machine must not drop a sample
            "umad/t/x", congestion_control=zenoh.CongestionControl.BLOCK
        )
        deadline = time.monotonic() + 10
        while not put.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        shm = ZenohShmPayloads(pool_mib=4)
        sent = [payload(1 << 20, fill) for fill in range(6)]
        packed = [shm.pack(p) for p in sent]  # held here, so the pool (3 such buffers) fills up
        assert shm.through_sockets > 0 and packed[-1] is sent[-1]
        assert shm.pack(payload(100)) == payload(100)  # small ones travel as they are
        for each in packed:
            put.put(each)
        deadline = time.monotonic() + 30
        while len(received) < len(sent) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert received == sent
        listener.undeclare()
    finally:
        for session in (publisher, subscriber, hub):
            session.close()


def test_without_room_for_a_zenoh_pool_payloads_go_as_they_are(monkeypatch):
    def no_room(size):
        raise zenoh.ZError("no space left on device")

    monkeypatch.setattr("umad_common.dataflow.transport.planes.zenoh_shm.ShmProvider.default_backend", no_room)
    shm = ZenohShmPayloads(pool_mib=64)
    large = payload(1 << 20)
    assert shm.pack(large) is large and "no 64 MiB pool" in shm.disabled_because
