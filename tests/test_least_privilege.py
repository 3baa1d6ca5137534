"""Least privilege that holds, tried from another network namespace against a real hub with real
certificates: an ordered operator's certificate can stop no source nor change its parameters, a
forged ack or goodbye changes nothing, and a worker holding only its operator's bundle runs that
operator and can do nothing else. Each intruder is a bare zenoh-python client (tests/intruder.py);
with each, the graph's results equal those of a run without it, bit for bit. Needs root; skipped
otherwise."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import pytest
import yaml

from tests.conftest import REPO, DrainedUmad, free_port, run_umad, umad_env
from tests.test_distributed import frames_done_by, in_namespace, remote_worker, secured
from tests.test_runtime_e2e import assert_exactly_once, sink_lines
from umad_common.dataflow.api.graph import load_graph
from umad_common.dataflow.launch.access import role_rules

pytestmark = pytest.mark.slow

FRAMES = 60  # per run, two runs
STOP = json.dumps({"stop": True}).encode()
SET = json.dumps({"set": {"frames": 3, "window": 1}}).encode()  # either would shorten the runs


def guarded_graph(folder: Path, hub: str) -> Path:
    """The toy graph with an ordered operator (`sum`) beside the stateless ones, each sink logging."""
    data = {
        "name": "toy",
        "hub": hub,
        "operators": [
            {
                "id": "source",
                "uses": "tests.toy_ops:RewindableCounterSource",
                "params": {"frames": FRAMES, "runs": 2, "window": 4},
            },
            {
                "id": "double",
                "uses": "tests.toy_ops:Scale",
                "inputs": {"x": "source/value"},
                "params": {"delay_s": 0.05},
            },
            {"id": "triple", "uses": "tests.toy_ops:Scale", "inputs": {"x": "source/value"}, "params": {"factor": 3}},
            {"id": "sum", "uses": "tests.toy_ops:RunningSum", "inputs": {"x": "source/value"}},
            {
                "id": "sink",
                "uses": "tests.toy_ops:JoinSink",
                "inputs": {"a": "source/value", "b": "*le/y"},
                "params": {"log": str(folder / "sink.jsonl")},
            },
            {
                "id": "sum_log",
                "uses": "tests.toy_ops:Logger",
                "inputs": {"x": "sum/y"},
                "params": {"log": str(folder / "sum.jsonl")},
            },
        ],
    }
    path = folder / "graph.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def results(folder: Path) -> tuple[list[str], list[str]]:
    """What the sinks wrote, in a fixed order: the joined totals, and the running sums without the
    process id that made each."""
    sums = [{k: v for k, v in json.loads(line).items() if k != "pid"} for line in (folder / "sum.jsonl").open()]
    return sorted((folder / "sink.jsonl").read_text().splitlines()), sorted(json.dumps(s) for s in sums)


@pytest.fixture(scope="module")
def undisturbed(tmp_path_factory) -> tuple[list[str], list[str]]:
    """The results of the graph run without any intruder (on a loopback hub: the bytes do not depend on it)."""
    folder = tmp_path_factory.mktemp("undisturbed")
    done = run_umad("launch", str(guarded_graph(folder, f"tcp/127.0.0.1:{free_port()}")), timeout=240)
    assert done.returncode == 0, done.stdout + done.stderr
    return results(folder)


def wait_for_frames(folder: Path, at_least: int = 5, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if (folder / "sink.jsonl").exists() and len(sink_lines(folder)) >= at_least:
            return
        time.sleep(0.05)


def intruder(ns: str, hub: str, bundle: Path, seconds: float, plan: dict, plan_file: Path) -> subprocess.Popen:
    """tests/intruder.py on the other host, holding `bundle` and carrying out `plan` (payloads as bytes)."""
    as_hex = {kind: [[key, payload.hex()] for key, payload in plan.get(kind, [])] for kind in ("puts", "queries")}
    plan_file.write_text(json.dumps({"listen": plan.get("listen", "umad/toy/**"), **as_hex}))
    cmd = ["ip", "netns", "exec", ns, sys.executable, "-m", "tests.intruder", hub, str(bundle), str(seconds)]
    return subprocess.Popen(
        [*cmd, str(plan_file)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=umad_env(), cwd=REPO
    )


def attacked(tmp_path: Path, netns, holder: str, plan, seconds: float = 5.0, meanwhile=None) -> tuple[str, dict]:
    """Launch the secured graph, let an intruder holding `holder`'s bundle carry out `plan(graph)`
    once frames flow, call `meanwhile(graph)`; returns the launcher's output and what the intruder saw."""
    ns, host_ip = netns
    hub = f"tls/{host_ip}:{free_port()}"
    graph = secured(guarded_graph(tmp_path, hub))
    launch = DrainedUmad("launch", str(graph))
    wait_for_frames(tmp_path)
    attack = intruder(ns, hub, tmp_path / "certs" / holder, seconds, plan(load_graph(graph)), tmp_path / "plan.json")
    if meanwhile is not None:
        meanwhile(graph)
    attack_out, _ = attack.communicate(timeout=120)
    out = launch.wait(timeout=240)
    assert launch.proc.returncode == 0, out
    assert attack.returncode == 0, attack_out
    return out, json.loads(attack_out.splitlines()[-1])


def writable_keys(graph, op: str) -> list[str]:
    """Every key operator `op`'s certificate may put on, each `*` as replica r0."""
    rules = role_rules(graph, f"operator:{op}")
    keys = {key for r in rules if "put" in r["messages"] and "ingress" in r["flows"] for key in r["key_exprs"]}
    return sorted(key.replace("*", "r0") for key in keys)


def test_an_ordered_operators_certificate_can_neither_stop_nor_set_a_source(tmp_path, netns, undisturbed):
    def plan(graph):
        keys = writable_keys(graph, "sum")
        assert "umad/toy/_resend/source" in keys  # the one right it has over the source: asking for frames
        targets = [*keys, "umad/toy/_ctl/source"]
        return {
            "puts": [(key, payload) for key in targets for payload in (STOP, SET)],
            "queries": [("umad/toy/_ctl/source", STOP), ("umad/toy/_ctl/source", SET)],
        }

    out, seen = attacked(tmp_path, netns, "op-sum", plan)
    assert seen["sent"] > 0 and seen["answers"] == [] and seen["seen"] == []
    assert "stop requested" not in out and "parameters changed" not in out
    assert_exactly_once(tmp_path, FRAMES)
    assert results(tmp_path) == undisturbed
    assert "access control refused op-sum: Query (ingress) on umad/toy/_ctl/source" in out, out
    ignored = "[source.0] WARNING umad.source: ignored a message on umad/toy/_resend/source: not a resend request"
    assert out.count(ignored) == 1, out  # logged once, though sent again and again


def forged_acks(graph) -> dict:
    """Acks of every frame as each sink: on the sinks' own keys, and on the intruder's own key."""
    frames = [(run, seq) for run in ("run0", "run1") for seq in range(FRAMES + 1)]  # + the end-of-run marker
    puts = []
    for sink in graph.sinks():
        for key in (f"umad/toy/_ack/{sink}/r0", "umad/toy/_ack/double/r0"):
            puts += [(key, msgpack.packb({"run": run, "seq": seq, "op": sink})) for run, seq in frames]
    return {"puts": puts}


def test_forged_acks_are_refused_or_ignored_and_a_lossless_source_delivers_every_frame(tmp_path, netns, undisturbed):
    out, seen = attacked(tmp_path, netns, "op-double", forged_acks)
    assert seen["sent"] > 0
    assert_exactly_once(tmp_path, FRAMES)
    assert results(tmp_path) == undisturbed
    for sink in ("sink", "sum_log"):
        assert f"access control refused op-double: Put (ingress) on umad/toy/_ack/{sink}/r0" in out, out
    ignored = "[source.0] WARNING umad.source: ignored a message on umad/toy/_ack/double/r0: claims to come from"
    assert out.count(ignored) == 1, out


def test_a_forged_goodbye_leaves_a_crashed_replica_in_place_until_it_is_back(tmp_path, netns, undisturbed):
    """`triple` is killed while an intruder says goodbye in its name: the sink still waits for the
    restarted `triple` (a goodbye would have it complete frames without `triple`'s maps)."""
    goodbye = msgpack.packb({"op": "triple", "replica": "r0"})
    plan = {"puts": [("umad/toy/_left/triple/r0", goodbye), ("umad/toy/_left/double/r0", goodbye)]}

    def kill_triple(graph: Path) -> None:
        time.sleep(0.5)  # the intruder's first goodbyes are out
        found = subprocess.run(["pgrep", "-f", "--", f"--graph {graph} --op triple"], capture_output=True, text=True)
        os.kill(int(found.stdout.split()[0]), signal.SIGKILL)

    out, seen = attacked(tmp_path, netns, "op-double", lambda graph: plan, seconds=8.0, meanwhile=kill_triple)
    assert seen["sent"] > 0
    assert "[triple.0] exited with -9; restart 1/3" in out, out
    assert_exactly_once(tmp_path, FRAMES)
    assert results(tmp_path) == undisturbed
    assert "access control refused op-double: Put (ingress) on umad/toy/_left/triple/r0" in out, out
    assert "[sink.0] WARNING umad.sink: ignored a message on umad/toy/_left/double/r0: claims to come from" in out


def test_a_worker_holding_only_its_bundle_runs_its_operator_and_can_do_nothing_else(tmp_path, netns, undisturbed):
    ns, host_ip = netns
    hub = f"tls/{host_ip}:{free_port()}"
    graph = secured(guarded_graph(tmp_path, hub))
    worker = tmp_path / "worker"  # the worker host's files: the graph file and one bundle, as the README copies them
    shutil.copytree(tmp_path / "certs/op-double", worker / "certs/op-double")
    shutil.copy(graph, worker / "graph.yaml")
    assert sorted(p.name for p in (worker / "certs").rglob("*") if p.is_file()) == [
        "ca.pem",
        "op-double.key",
        "op-double.pem",
    ]
    assert (worker / "certs/op-double/op-double.key").stat().st_mode & 0o777 == 0o600
    launch = DrainedUmad("launch", str(graph))
    wait_for_frames(tmp_path)
    replica = remote_worker(ns, worker / "graph.yaml", "double", 1, hub)
    others = [
        *(f"umad/toy/{op}/{out}" for op, out in (("source", "value"), ("triple", "y"), ("sum", "y"))),
        "umad/toy/_ack/sink/r0",
        "umad/toy/_left/triple/r0",
        "umad/toy/_resend/source",
        "umad/toy/_ctl/source",
    ]
    plan = {
        "puts": [(key, payload) for key in others for payload in (STOP, SET)],
        "queries": [(f"umad/toy/_ctl/{op}", STOP) for op in ("source", "triple", "double", "_launcher")]
        + [("umad/toy/_graph", b"{}"), ("umad/*/_graph", b"{}")],
    }
    attack = intruder(ns, hub, worker / "certs/op-double", 5.0, plan, tmp_path / "plan.json")
    own = ["--graph", str(worker / "graph.yaml")]
    commands = [in_namespace(ns, "set", "triple.factor=5", *own), in_namespace(ns, "op", "stop", "source", *own)]
    attack_out, _ = attack.communicate(timeout=120)
    refused = [command.communicate(timeout=60)[0] for command in commands]
    out = launch.wait(timeout=240)
    replica.send_signal(signal.SIGTERM)
    replica_out, _ = replica.communicate(timeout=30)

    assert launch.proc.returncode == 0, out
    assert frames_done_by(replica_out) > 0, replica_out  # it ran its operator with its bundle alone
    seen = json.loads(attack_out.splitlines()[-1])
    assert seen["sent"] > 0 and seen["answers"] == [] and seen["seen"] == [], seen
    for text, command in zip(refused, commands, strict=True):
        assert command.returncode != 0 and "control/ca.pem" in text and "is not a file" in text, text
    for refusal in ("Put (ingress) on umad/toy/triple/y", "Query (ingress) on umad/toy/_ctl/_launcher"):
        assert f"access control refused op-double: {refusal}" in out, out
    assert results(tmp_path) == undisturbed
    assert_exactly_once(tmp_path, FRAMES)
