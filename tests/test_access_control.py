"""Only the graph's certificates get in, and each does only what its role allows: mutual TLS and the
hub's Zenoh access control, tried from another network namespace (tests/test_distributed.py's
second "host") against a real hub and real processes. Needs root; skipped otherwise."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import REPO, DrainedUmad, free_port, run_umad, umad_env
from tests.test_distributed import in_namespace, remote_worker, secure_graph
from tests.test_runtime_e2e import assert_exactly_once, sink_lines

pytestmark = pytest.mark.slow


def wait_for_frames(tmp_path: Path, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while not ((tmp_path / "sink.jsonl").exists() and sink_lines(tmp_path)) and time.monotonic() < deadline:
        time.sleep(0.1)


def remote_client(ns: str, mode: str, hub: str, certs: Path, name: str, seconds: float) -> subprocess.Popen:
    """tests/remote_client.py on the other host, presenting certificate `name`."""
    bundle = certs / name
    cmd = ["ip", "netns", "exec", ns, sys.executable, "-m", "tests.remote_client", mode, hub, str(bundle / "ca.pem")]
    cmd += [str(bundle / f"{name}.pem"), str(bundle / f"{name}.key"), str(seconds)]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=umad_env(), cwd=REPO)


def finished(proc: subprocess.Popen, timeout_s: float = 60) -> tuple[int, str]:
    out, _ = proc.communicate(timeout=timeout_s)
    return proc.returncode, out


def test_a_worker_without_a_certificate_of_the_graphs_ca_gets_no_frame_and_is_refused(tmp_path, netns):
    ns, host_ip = netns
    hub = f"tls/{host_ip}:{free_port()}"
    graph = secure_graph(tmp_path, host_ip, int(hub.rpartition(":")[2]), frames=60, delay=0.05)
    without_certs = yaml.safe_load(graph.read_text())
    del without_certs["tls"]["certs"]  # this host holds the CA, but no certificate of its own
    bare = tmp_path / "bare.yaml"
    bare.write_text(yaml.safe_dump(without_certs, sort_keys=False))
    other = tmp_path / "other"
    other.mkdir()
    foreign = run_umad("certs", str(graph), "--out", str(other / "certs"))  # a CA of its own, same names
    assert foreign.returncode == 0, foreign.stderr
    launch = DrainedUmad("launch", str(graph))
    wait_for_frames(tmp_path)
    started = time.monotonic()
    no_cert = remote_worker(ns, bare, "double", 1, hub)
    other_ca = remote_worker(
        ns,
        graph,
        "double",
        2,
        hub,
        "--cert",
        str(other / "certs/op-double/op-double.pem"),  # the ca.pem beside it is the other CA's
        "--key",
        str(other / "certs/op-double/op-double.key"),
    )
    for worker in (no_cert, other_ca):
        code, out = finished(worker, timeout_s=30)
        lines = [line for line in out.splitlines() if line.strip()]
        assert code != 0 and len(lines) == 1, out
        assert "could not join: the hub at" in lines[0] and "refused the TLS handshake" in lines[0], out
    assert time.monotonic() - started < 20  # refused at once, no waiting for a hub that will never take it
    out = launch.wait(timeout=180)
    assert launch.proc.returncode == 0, out
    assert_exactly_once(tmp_path, 60)


def test_an_operator_certificate_cannot_command_nor_publish_as_another_operator(tmp_path, netns):
    ns, host_ip = netns
    port = free_port()
    hub = f"tls/{host_ip}:{port}"
    graph = secure_graph(tmp_path, host_ip, port, frames=80, delay=0.0)
    baseline = DrainedUmad("launch", str(graph))
    out = baseline.wait(timeout=180)
    assert baseline.proc.returncode == 0, out
    without_intruder = sorted((tmp_path / "sink.jsonl").read_text().splitlines())
    (tmp_path / "sink.jsonl").unlink()
    data = yaml.safe_load(graph.read_text())
    data["operators"][1]["params"]["delay_s"] = 0.1  # long enough for the intruder to try everything
    graph.write_text(yaml.safe_dump(data, sort_keys=False))

    launch = DrainedUmad("launch", str(graph))
    wait_for_frames(tmp_path)
    certs = tmp_path / "certs"
    bundle = certs / "op-double"
    own = ["--graph", str(graph), "--cert", str(bundle / "op-double.pem"), "--key", str(bundle / "op-double.key")]
    intruder = remote_client(ns, "intrude", hub, certs, "op-double", seconds=4)
    set_param = in_namespace(ns, "set", "triple.factor=5", *own)
    stop = in_namespace(ns, "op", "stop", "triple", *own)
    intruded = json.loads(finished(intruder)[1].splitlines()[-1])
    set_code, set_out = finished(set_param)
    stop_code, stop_out = finished(stop)
    out = launch.wait(timeout=180)

    assert launch.proc.returncode == 0, out
    assert intruded["sent"] > 0 and intruded["set_answers"] == [] and intruded["stop_answers"] == []
    assert set_code != 0 and "role control" in set_out, set_out
    assert stop_code != 0 and "role control" in stop_out, stop_out
    for refused in (
        "Put (ingress) on umad/toy/triple/y",
        "Put (ingress) on umad/toy/source/value",
        "Query (ingress) on umad/toy/_ctl/triple",
        "Query (ingress) on umad/toy/_ctl/_launcher",
        "Query (ingress) on umad/toy/_graph",
    ):
        assert f"access control refused op-double: {refused}" in out, out
    assert sorted((tmp_path / "sink.jsonl").read_text().splitlines()) == without_intruder
    assert_exactly_once(tmp_path, 80)


def test_an_observer_reads_every_channel_and_cannot_publish_and_control_reaches_the_operators_and_launcher(
    tmp_path, netns
):
    ns, host_ip = netns
    port = free_port()
    hub = f"tls/{host_ip}:{port}"
    graph = secure_graph(tmp_path, host_ip, port, frames=60, delay=0.05)
    launch = DrainedUmad("launch", str(graph))
    wait_for_frames(tmp_path)
    observer = remote_client(ns, "observe", hub, tmp_path / "certs", "observer", seconds=3)
    control = in_namespace(ns, "set", "double.factor=2", "--graph", str(graph))  # `control` of tls.certs
    start = in_namespace(ns, "op", "start", "double", "--graph", str(graph))
    seen = json.loads(finished(observer)[1].splitlines()[-1])["seen"]
    control_code, control_out = finished(control)
    start_code, start_out = finished(start)
    out = launch.wait(timeout=180)

    assert launch.proc.returncode == 0, out
    channels = {"umad/toy/source/value", "umad/toy/double/y", "umad/toy/triple/y", "umad/toy/sink/total"}
    assert channels <= set(seen), seen
    assert {"umad/toy/_ack/sink/r0"} <= set(seen) and any(key.startswith("umad/toy/_stats/") for key in seen), seen
    assert "access control refused observer: Put (ingress) on umad/toy/source/value" in out, out
    assert control_code == 0 and "double.r0: applied" in control_out, control_out
    assert start_code == 1 and "double: refused: double is already running" in start_out, start_out  # it got there
    assert_exactly_once(tmp_path, 60)
