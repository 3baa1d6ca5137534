"""Plane `ring`: payloads written once into a publisher's shared-memory ring, references through
Zenoh, fetched from the publisher where the ring cannot be mapped. What every plane does alike is
in test_planes.py."""

from __future__ import annotations

import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO, run_umad, start_umad, umad_env
from tests.test_distributed import frames_done_by
from tests.test_planes import large_toy_graph, payload
from tests.test_runtime_e2e import assert_exactly_once, sink_lines, toy_graph
from umad_common.dataflow.api.messages import MessageError, decode
from umad_common.dataflow.record.mcap_log import read_log
from umad_common.dataflow.transport.bus import open_client, open_hub
from umad_common.dataflow.transport.planes import INLINE_BELOW
from umad_common.dataflow.transport.planes.ring import (
    RING_DIR,
    PayloadReader,
    PayloadRing,
    fetch,
    is_reference,
    remove_stale_rings,
)


def test_a_large_payload_travels_as_a_reference_and_comes_back_byte_for_byte(tmp_path):
    ring, reader = PayloadRing("umad/t", tmp_path), PayloadReader(tmp_path)
    small, large = payload(100), payload(1 << 20, 7)
    assert ring.pack(small) == small and reader.take(small) == small  # small ones travel inline
    reference = ring.pack(large)
    assert is_reference(reference) and len(reference) < 100
    assert reader.take(reference) == large
    with pytest.raises(MessageError, match="not valid msgpack"):  # never mistaken for a message
        decode(reference)
    ring.close()
    assert not list(tmp_path.iterdir())


def test_an_overwritten_payload_is_refused_not_returned_torn(tmp_path):
    ring, reader = PayloadRing("umad/t", tmp_path), PayloadReader(tmp_path)
    first = ring.pack(payload(INLINE_BELOW, 1))
    assert reader.take(first) == payload(INLINE_BELOW, 1)
    for fill in range(2, 200):  # round the ring several times
        latest = ring.pack(payload(INLINE_BELOW, fill))
    assert reader.take(first) is None
    assert reader.take(latest) == payload(INLINE_BELOW, 199)
    ring.close()


def test_the_ring_grows_for_a_larger_payload_and_the_old_one_goes_at_the_next_growth(tmp_path):
    ring, reader = PayloadRing("umad/t", tmp_path), PayloadReader(tmp_path)
    small = payload(INLINE_BELOW, 1)
    before = ring.pack(small)
    first_name, first_capacity = ring.name, ring.capacity
    big = payload(ring.capacity // 8, 2)  # needs 32 slots: more than the ring holds
    after = ring.pack(big)
    assert ring.name != first_name and ring.capacity > first_capacity
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([first_name, ring.name])
    assert reader.take(after) == big
    assert reader.take(before) == small  # a reader mapping the old ring only now still reads it
    latest = PayloadReader(tmp_path)
    bigger = payload(ring.capacity // 8, 3)
    last = ring.pack(bigger)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([ring.previous_name, ring.name])
    assert first_name not in {ring.previous_name, ring.name}
    assert latest.take(before) is None  # gone before this reader mapped it: fetch from the publisher
    assert latest.take(after) == big and latest.take(last) == bigger
    ring.close()
    assert list(tmp_path.iterdir()) == []


def test_a_ring_that_cannot_be_created_sends_payloads_inline(tmp_path):
    ring = PayloadRing("umad/t", tmp_path / "missing")
    large = payload(1 << 20)
    assert ring.pack(large) == large
    assert "cannot create" in ring.disabled_because


def test_a_taken_payload_is_a_copy_its_decoded_arrays_outlive_the_ring_going_round(tmp_path):
    ring, reader = PayloadRing("umad/t", tmp_path), PayloadReader(tmp_path)
    message = decode(reader.take(ring.pack(payload(INLINE_BELOW, 1))))
    for fill in range(2, 200):  # round the ring several times
        ring.pack(payload(INLINE_BELOW, fill))
    assert message.seq == 1 and (message.arrays["x"] == 1).all()
    ring.close()


def _write_round_and_round(directory: str, references, rounds: int) -> None:
    """A publisher process: payloads whose every byte is their seq, their references sent at once."""
    ring = PayloadRing("umad/t", Path(directory))
    for seq in range(rounds):
        references.put(ring.pack(payload(INLINE_BELOW, seq % 256)))
    references.put(None)
    ring.close(unlink=False)


def test_a_payload_overwritten_while_a_reader_copies_it_is_never_accepted_torn(tmp_path):
    """A publisher in another process goes round its ring while this reader copies payloads out:
    whatever the interleaving, an accepted payload is whole (every byte its own seq), never a mix."""
    spawn = multiprocessing.get_context("spawn")
    references = spawn.Queue()
    writer = spawn.Process(target=_write_round_and_round, args=(str(tmp_path), references, 3000))
    writer.start()
    reader, accepted, refused = PayloadReader(tmp_path), 0, 0
    try:
        while (reference := references.get(timeout=60)) is not None:
            taken = reader.take(reference)
            if taken is None:
                refused += 1
                continue
            message = decode(taken)
            assert (message.arrays["x"] == message.seq).all(), f"torn payload accepted: seq {message.seq}"
            accepted += 1
    finally:
        writer.join(30)
        reader.close()
    assert accepted + refused == 3000 and accepted > 0


@pytest.mark.parametrize("machine", ["aarch64", "arm64", "riscv64", "ppc64le"])
def test_on_a_cpu_without_x86_memory_order_no_ring_is_made(tmp_path, monkeypatch, machine):
    monkeypatch.setattr("platform.machine", lambda: machine)
    ring = PayloadRing("umad/t", tmp_path)
    large = payload(1 << 20)
    assert ring.pack(large) == large and not list(tmp_path.iterdir())
    assert machine in ring.disabled_because


def test_a_reader_that_cannot_map_the_ring_fetches_from_the_publisher(tmp_path, hub_endpoint):
    hub = open_hub(hub_endpoint)
    publisher, subscriber = open_client(hub_endpoint), open_client(hub_endpoint)
    ring = PayloadRing("umad/t", tmp_path / "host_a")
    (tmp_path / "host_a").mkdir()
    try:
        queryable = publisher.declare_queryable(ring.fetch_key, ring.serve)
        large = payload(1 << 20, 3)
        reference = ring.pack(large)
        elsewhere = PayloadReader(tmp_path / "host_b")  # another host: the ring's file is not there
        assert elsewhere.take(reference) is None
        deadline = time.monotonic() + 10  # the queryable's declaration reaches the hub after a while
        while (fetched := fetch(subscriber, "umad/t", reference)) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert fetched == large
        for fill in range(100):  # the publisher keeps only its last payloads
            ring.pack(payload(INLINE_BELOW, fill))
        assert fetch(subscriber, "umad/t", reference) is None
        queryable.undeclare()
    finally:
        ring.close()
        for session in (publisher, subscriber, hub):
            session.close()


def test_rings_of_dead_processes_are_removed_and_live_ones_kept(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f"umad-{dead.stdout.strip()}-00ff-1.ring"
    live = tmp_path / f"umad-{os.getpid()}-00ff-1.ring"
    stale.write_bytes(b"x")
    live.write_bytes(b"x")
    assert remove_stale_rings(tmp_path) == [stale.name]
    assert live.exists()


def test_a_recording_holds_the_payloads_and_replays_byte_for_byte(tmp_path, hub_endpoint):
    graph = large_toy_graph(tmp_path, hub_endpoint, frames=12)
    first, second = tmp_path / "first.mcap", tmp_path / "second.mcap"
    result = run_umad("launch", str(graph), "--record", str(first), timeout=120)
    assert result.returncode == 0, result.stdout
    assert_exactly_once(tmp_path, 12)
    records = [r for r in read_log(first) if r.topic.startswith("umad/toy/source/")]
    assert len(records) >= 26 and not any(is_reference(r.data) for r in records)
    assert {decode(r.data).arrays["x"].nbytes for r in records if not decode(r.data).meta.get("eos")} == {400_000}
    result = run_umad("replay", str(first), "--graph", str(graph), "--record", str(second), timeout=120)
    assert result.returncode == 0, result.stdout

    def sink_payloads(path):
        return sorted(r.data for r in read_log(path) if r.topic == "umad/toy/sink/total")

    assert sink_payloads(first) == sink_payloads(second)
    assert not remove_stale_rings()  # every replica unlinked its ring on the way out


def test_a_ring_left_to_the_launcher_still_gives_its_payloads_after_its_publisher_closed(tmp_path):
    """On a busy machine the recorder's callbacks run late: the source has had its frames acked and
    exited before the recorder copies their payloads, perhaps before it first mapped the ring. A
    replica the launcher started leaves its ring to the launcher's sweep, so the copy still works."""
    ring, reader = PayloadRing("umad/test", tmp_path), PayloadReader(tmp_path)
    sent = [payload(INLINE_BELOW * 2, fill) for fill in range(3)]
    references = [ring.pack(p) for p in sent]
    ring.close(unlink=False)
    assert [reader.take(r) for r in references] == sent  # mapped for the first time after the close
    reader.close()
    ring = PayloadRing("umad/test", tmp_path)
    reference = ring.pack(sent[0])
    ring.close()  # a replica on its own (`umad op run`) unlinks its ring
    assert not (tmp_path / ring.name).exists() and PayloadReader(tmp_path).take(reference) is None


def test_the_launcher_sweeps_a_replicas_ring_only_after_a_grace(tmp_path, hub_endpoint, monkeypatch):
    from umad_common.dataflow.api.graph import load_graph
    from umad_common.dataflow.launch import launcher

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    ring_file = RING_DIR / f"umad-{pid}-00ff-1.ring"
    ring_file.write_bytes(b"x")
    graph_file = toy_graph(tmp_path, hub_endpoint)
    sweeper = launcher.Launcher(load_graph(graph_file), graph_file, quiet=True)
    try:
        sweeper._exited[pid] = time.monotonic()
        sweeper._sweep_rings()
        assert ring_file.exists()  # the recorder may still copy from it
        sweeper._exited[pid] = time.monotonic() - launcher.RING_GRACE_S - 1
        sweeper._sweep_rings()
        assert not ring_file.exists() and not sweeper._exited
    finally:
        ring_file.unlink(missing_ok=True)


def test_a_worker_on_another_host_fetches_and_serves_payloads(tmp_path, hub_endpoint):
    """A second replica whose rings live where the others cannot map them (another host, as far as
    shared memory goes) joins mid-stream: it fetches its inputs from the source and the sink fetches
    its outputs from it. Every frame still arrives exactly once."""
    graph = large_toy_graph(tmp_path, hub_endpoint, frames=60, delay=0.03, replicas=1)
    proc = start_umad("launch", str(graph))
    deadline = time.monotonic() + 60
    while not ((tmp_path / "sink.jsonl").exists() and sink_lines(tmp_path)) and time.monotonic() < deadline:
        time.sleep(0.1)
    other_host = tmp_path / "other_host_shm"
    other_host.mkdir()
    cmd = [sys.executable, "-m", "umad_common.cli", "op", "run", "double", "--graph", str(graph), "--replica", "1"]
    env = {**umad_env(), "UMAD_RING_DIR": str(other_host)}
    worker = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO)
    out, _ = proc.communicate(timeout=180)
    worker.send_signal(signal.SIGTERM)
    worker_out, _ = worker.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert frames_done_by(worker_out) > 0, worker_out
    assert "could not be fetched" not in out + worker_out
    assert_exactly_once(tmp_path, 60)
    assert not list(other_host.iterdir())  # the worker unlinked its ring on the way out
