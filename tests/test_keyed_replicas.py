"""Keyed replicas of an ordered operator: each run belongs to one replica, chosen by rendezvous
hashing over the replicas alive at the run's start; a dead replica's runs move to a survivor, which
re-observes them from their first frame, so the results equal a one-replica run.

The end-to-end tests run a running sum (a stateful toy operator) in two replicas on four runs sent
side by side (`runs_in_flight`); the values a fault-free run gives are known in closed form."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import threading
import time
from collections import defaultdict
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from tests.conftest import free_port, run_umad, start_umad
from umad_common import DEFAULT_GRAPH
from umad_common.dataflow.api.graph import validate_graph
from umad_common.dataflow.api.messages import Message, decode, encode
from umad_common.dataflow.delivery.joiner import Membership
from umad_common.dataflow.delivery.ordered import RunOwners, rendezvous_score
from umad_common.dataflow.delivery.service_messages import IgnoredMessages, encode_ack
from umad_common.dataflow.delivery.stats import Stats
from umad_common.dataflow.process.source_driver import SourceDriver
from umad_common.dataflow.transport.bus import Keys

RUNS = [f"run{r}" for r in range(4)]


def highest(run: str, replicas: set[str]) -> str:
    return max(replicas, key=lambda replica: rendezvous_score(run, replica))


def test_replicas_deciding_alone_agree_on_each_runs_owner_and_share_the_runs():
    r0, r1 = RunOwners("r0"), RunOwners("r1")
    alive = {"r0", "r1"}
    owners = {run: r0.owner(run, 0, alive) for run in RUNS}
    assert owners == {run: r1.owner(run, 0, alive) for run in RUNS}
    assert owners == {run: highest(run, alive) for run in RUNS}
    assert set(owners.values()) == {"r0", "r1"}  # these four runs give both replicas work (e2e tests below)


def test_a_replica_that_joins_later_takes_only_runs_that_start_after_it():
    r0 = RunOwners("r0")
    before = {run: r0.owner(run, 0, {"r0", "r1"}) for run in RUNS}
    newcomer = RunOwners("r2")
    everyone = {"r0", "r1", "r2"}
    for run in RUNS:  # under way: the newcomer first sees them mid-run, r0 saw them start without it
        assert r0.owner(run, 7, everyone) == before[run]
        assert newcomer.owner(run, 7, everyone) == before[run]
    later = [f"late{i}" for i in range(12)]
    owners = {run: r0.owner(run, 0, everyone) for run in later}
    assert owners == {run: newcomer.owner(run, 0, everyone) for run in later}
    assert "r2" in owners.values()


def test_a_replica_whose_own_token_has_not_come_back_leaves_a_starting_run_to_the_others():
    """Until its token is back from the hub, the others may not know this replica: a run starting then
    is not counted as its own."""
    late = RunOwners("r1")
    run = next(run for run in (f"x{i}" for i in range(100)) if highest(run, {"r0", "r1"}) == "r1")
    assert late.owner(run, 0, {"r0"}) == "r0"
    assert late.owner(run, 1, {"r0", "r1"}) == "r0"  # and it stays theirs once the token is seen


def test_a_dead_replicas_runs_move_to_the_survivor_and_stay_there_when_it_restarts():
    r0 = RunOwners("r0")
    owners = {run: r0.owner(run, 0, {"r0", "r1"}) for run in RUNS}
    taken = r0.replica_gone("r1", {"r0"})
    assert sorted(taken) == sorted(run for run, owner in owners.items() if owner == "r1")
    assert all(r0.owner(run, 9, {"r0"}) == "r0" for run in RUNS)
    restarted = RunOwners("r1")  # the launcher restarted r1: a new process with the same name
    for run in RUNS:
        assert r0.owner(run, 12, {"r0", "r1"}) == "r0"
        assert restarted.owner(run, 12, {"r0", "r1"}) == "r0"
    assert r0.replica_gone("r1", {"r0"}) == []  # nothing was r1's any more


def test_the_graph_check_accepts_keyed_replicas_of_the_world_model():
    data = yaml.safe_load(DEFAULT_GRAPH.read_text())
    data["base_dir"] = str(DEFAULT_GRAPH.resolve().parent)
    for op in data["operators"]:
        if op.get("kind") == "world_model":
            op["replicas"] = 2
        if op.get("kind") == "replayer":
            op["params"]["runs_in_flight"] = 4
    graph = validate_graph(data)
    assert graph.op("world_model").replicas == 2


def test_runs_side_by_side_need_lossless_pacing():
    data = {
        "name": "sbs",
        "operators": [
            {
                "id": "source",
                "uses": "tests.toy_ops:RewindableCounterSource",
                "params": {"pacing": "realtime", "runs_in_flight": 2},
            },
        ],
    }
    with pytest.raises(ValueError, match="runs_in_flight 2 needs pacing lossless"):
        validate_graph(data)


class AckingHost:
    """What the source driver needs of a runtime, without Zenoh: every published frame is acked by
    the graph's one sink at once, and the publishing order is kept."""

    def __init__(self, graph):
        self.graph = graph
        self.op_id = "source"
        self.log = logging.getLogger("test.source")
        self.stats = Stats()
        self.shutdown = threading.Event()
        self.members = Membership()
        for op in graph.spec.operators:
            self.members.put(op.id, "r0")
        self.resend_requests: list[dict] = []
        self.ignored = IgnoredMessages(self.log, self.stats)
        self.published: list[tuple[str, int, bool]] = []  # (run, seq, end-of-run marker)
        self.on_ack = None

    def subscribe(self, key, callback):
        self.on_ack = callback

    def handle_service(self):
        return False

    def publish_stats(self, force=False):
        pass

    def count_cpu_from_now(self):
        pass

    def encode_outputs(self, run, seq, stamp_ns, outputs, extra_meta):
        return [
            (port, encode(Message(run, seq, stamp_ns, "source", extra_meta, out.arrays)))
            for port, out in outputs.items()
        ]

    def markers(self, run, seq, stamp_ns, meta):
        return [("value", encode(Message(run, seq, stamp_ns, "source", meta)))]

    def publish(self, payloads, count=True):
        msg = decode(payloads[0][1])
        self.published.append((msg.run, msg.seq, bool(msg.meta.get("eos"))))
        ack = encode_ack(msg.run, msg.seq, "log")
        self.on_ack(
            SimpleNamespace(key_expr=Keys("sbs").ack("log", "r0"), payload=SimpleNamespace(to_bytes=lambda: ack))
        )


def test_a_source_sends_runs_side_by_side_and_ends_each_once_its_frames_are_acked():
    graph = validate_graph(
        {
            "name": "sbs",
            "operators": [
                {
                    "id": "source",
                    "uses": "tests.toy_ops:RewindableCounterSource",
                    "params": {"runs": 3, "frames": 5, "window": 2, "runs_in_flight": 2},
                },
                {"id": "log", "uses": "tests.toy_ops:Logger", "inputs": {"x": "source/value"}},
            ],
        }
    )
    host = AckingHost(graph)
    SourceDriver(host, graph.classes["source"](graph.op("source").params), graph).run()
    frames = [(run, seq) for run, seq, eos in host.published if not eos]
    assert sorted(frames) == [(f"run{r}", s) for r in range(3) for s in range(5)]
    assert frames.index(("run1", 0)) < frames.index(("run0", 4))  # the first two runs' frames take turns
    open_runs, most_open = set(), 0
    for run, seq, eos in host.published:
        if eos:
            assert seq == 5 and run in open_runs  # after every frame of its run
            open_runs.discard(run)
        else:
            open_runs.add(run)
            most_open = max(most_open, len(open_runs))
    assert not open_runs and most_open == 2
    assert [run for run, _, eos in host.published if eos] == ["run0", "run1", "run2"]


# -- end to end ------------------------------------------------------------------------------------


def keyed_graph(tmp_path: Path, hub: str, frames: int, delay: float, replicas: int, runs_in_flight: int) -> Path:
    data = {
        "name": "keyed",
        "hub": hub,
        "operators": [
            {
                "id": "source",
                "uses": "tests.toy_ops:RewindableCounterSource",
                "params": {
                    "frames": frames,
                    "runs": len(RUNS),
                    "window": 4,
                    "ack_timeout_s": 5.0,
                    "runs_in_flight": runs_in_flight,
                },
            },
            {
                "id": "cumsum",
                "uses": "tests.toy_ops:RunningSum",
                "inputs": {"x": "source/value"},
                "replicas": replicas,
                "params": {"delay_s": delay},
            },
            {
                "id": "log",
                "uses": "tests.toy_ops:Logger",
                "inputs": {"x": "cumsum/y"},
                "params": {"log": str(tmp_path / "log.jsonl")},
            },
        ],
    }
    graph = tmp_path / "graph.yaml"
    graph.write_text(yaml.safe_dump(data, sort_keys=False))
    return graph


def logged(tmp_path: Path) -> list[dict]:
    log = tmp_path / "log.jsonl"
    return [json.loads(x) for x in log.read_text().splitlines()] if log.exists() else []


def assert_values_of_a_fault_free_run(lines: list[dict], frames: int) -> None:
    """Every frame of every run logged, each line with the running sum a one-replica run gives (a
    frame re-observed after a takeover may be logged again, with the same value)."""
    expected = {(f"run{r}", s): float(sum(v + 1000 * r for v in range(s + 1))) for r in range(4) for s in range(frames)}
    assert {(x["run"], x["seq"]) for x in lines} == set(expected)
    wrong = [x for x in lines if x["value"] != expected[(x["run"], x["seq"])]]
    assert not wrong, wrong[:5]


def pids_per_run(lines: list[dict]) -> dict[str, set[int]]:
    pids = defaultdict(set)
    for x in lines:
        pids[x["run"]].add(x["pid"])
    return pids


@pytest.mark.slow
def test_each_run_is_computed_by_one_replica_and_both_replicas_work(tmp_path, hub_endpoint):
    frames = 30
    result = run_umad("launch", str(keyed_graph(tmp_path, hub_endpoint, frames, 0.02, 2, 4)), timeout=180)
    assert result.returncode == 0, result.stdout + result.stderr
    lines = logged(tmp_path)
    assert_values_of_a_fault_free_run(lines, frames)
    assert len(lines) == 4 * frames  # no frame computed twice
    pids = pids_per_run(lines)
    assert all(len(p) == 1 for p in pids.values()), pids  # a run's frames never interleave across replicas
    assert len(set.union(*pids.values())) == 2


@pytest.mark.slow
def test_sigkill_of_a_replica_moves_its_runs_and_the_values_equal_a_fault_free_run(tmp_path, hub_endpoint):
    frames = 60
    graph = keyed_graph(tmp_path, hub_endpoint, frames, 0.03, 2, 4)
    proc = start_umad("launch", str(graph))
    victim, deadline = None, time.monotonic() + 90
    while victim is None and time.monotonic() < deadline:
        out = subprocess.run(
            ["pgrep", "-f", "--", f"--graph {graph} --op cumsum --replica 1"], capture_output=True, text=True
        )
        if out.stdout.strip() and sum(x["run"] == "run1" for x in logged(tmp_path)) > 10:  # run1 is r1's
            victim = int(out.stdout.split()[0])
        time.sleep(0.05)
    assert victim, "replica 1 never computed run1"
    os.kill(victim, signal.SIGKILL)
    out, _ = proc.communicate(timeout=240)
    assert proc.returncode == 0, out
    assert "its replica is gone; taking it over from its first frame" in out
    lines = logged(tmp_path)
    assert_values_of_a_fault_free_run(lines, frames)
    survivor = {x["pid"] for x in lines if x["run"] == "run0"}
    assert {x["pid"] for x in lines if x["run"] == "run1" and x["seq"] == frames - 1} == survivor


@pytest.mark.slow
def test_keyed_replicas_in_two_network_namespaces_share_the_runs(tmp_path, netns):
    """Replica 0 on this host, replica 1 in another namespace joining over TCP once the graph runs:
    the runs that start after it joined are shared, each computed by one replica."""
    from tests.test_distributed import remote_worker

    ns, host_ip = netns
    hub = f"tcp/{host_ip}:{free_port()}"
    frames = 60
    graph = keyed_graph(tmp_path, hub, frames, 0.05, 1, 1)
    proc = start_umad("launch", str(graph))
    deadline = time.monotonic() + 60
    while not logged(tmp_path) and time.monotonic() < deadline:
        time.sleep(0.1)
    worker = remote_worker(ns, graph, "cumsum", 1, hub)
    out, _ = proc.communicate(timeout=240)
    worker.send_signal(signal.SIGTERM)
    worker_out, _ = worker.communicate(timeout=30)
    assert proc.returncode == 0, out
    lines = logged(tmp_path)
    assert_values_of_a_fault_free_run(lines, frames)
    pids = pids_per_run(lines)
    assert all(len(p) == 1 for p in pids.values()), pids
    assert len(set.union(*pids.values())) == 2, worker_out  # the remote replica computed runs
