"""Sessions on the bus: replicas on the hub's host link to each other directly (`direct_links`)."""

import queue
import time

from umad_common.dataflow.transport.bus import close_session, open_client, open_hub


def wait_for(condition, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_direct_links_carry_messages_between_replicas_without_the_hub(hub_endpoint):
    hub = open_hub(hub_endpoint)
    peer_a, peer_b = open_client(hub_endpoint, direct_links=True), open_client(hub_endpoint, direct_links=True)
    client_a, client_b = open_client(hub_endpoint), open_client(hub_endpoint)
    got: queue.Queue = queue.Queue()
    try:
        assert wait_for(lambda: peer_b.info.zid() in list(peer_a.info.peers_zid())), "the peers never linked"
        assert list(client_a.info.peers_zid()) == []  # a client knows only its hub
        peer_b.declare_subscriber("t/direct", lambda sample: got.put(("direct", sample.payload.to_bytes())))
        client_b.declare_subscriber("t/client", lambda sample: got.put(("client", sample.payload.to_bytes())))
        to_peer, to_client = peer_a.declare_publisher("t/direct"), client_a.declare_publisher("t/client")
        assert wait_for(lambda: to_peer.matching_status.matching and to_client.matching_status.matching)

        hub.close()
        to_peer.put(b"straight")
        to_client.put(b"through the hub")
        assert got.get(timeout=5) == ("direct", b"straight")
        time.sleep(1.0)
        assert got.empty()  # the clients' message had no hub to go through
    finally:
        for session in (peer_a, peer_b, client_a, client_b):
            close_session(session, timeout_s=2.0)
