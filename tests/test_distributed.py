"""Across hosts: a worker in another network namespace joins the hub over TCP; the hub can require
mutual TLS (tests/test_access_control.py: who gets in, and what each certificate may do).

The second "host" is a network namespace joined to this one by a veth pair (iproute2), so the
worker's only way to the hub is a real network link. Needs root (as CI has); skipped otherwise.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import REPO, free_port, namespace_ring_dir, run_umad, start_umad, umad_env
from tests.test_runtime_e2e import assert_exactly_once, sink_lines, toy_graph

pytestmark = pytest.mark.slow


def in_namespace(ns: str, *args: str) -> subprocess.Popen:
    """`umad ARGS` started on the other "host", with its own folder for payload rings."""
    cmd = ["ip", "netns", "exec", ns, sys.executable, "-m", "umad_common.cli", *args]
    env = {**umad_env(), "UMAD_RING_DIR": str(namespace_ring_dir(ns))}
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO)


def remote_worker(ns: str, graph: Path, op: str, replica: int, connect: str, *extra: str) -> subprocess.Popen:
    return in_namespace(
        ns, "op", "run", op, "--graph", str(graph), "--replica", str(replica), "--connect", connect, *extra
    )


def run_with_remote_replica(tmp_path: Path, ns: str, graph: Path, connect: str) -> tuple[str, str]:
    proc = start_umad("launch", str(graph))
    deadline = time.monotonic() + 60
    while not ((tmp_path / "sink.jsonl").exists() and sink_lines(tmp_path)) and time.monotonic() < deadline:
        time.sleep(0.1)
    worker = remote_worker(ns, graph, "double", 1, connect)  # joins mid-stream, as a user's extra machine would
    out, _ = proc.communicate(timeout=180)
    worker.send_signal(signal.SIGTERM)
    worker_out, _ = worker.communicate(timeout=30)
    assert proc.returncode == 0, out
    return out, worker_out


def frames_done_by(worker_out: str) -> int:
    line = next(line for line in worker_out.splitlines() if "stopped after" in line)
    return int(line.split("stopped after ")[1].split()[0])


def test_worker_in_another_namespace_joins_over_tcp_and_takes_frames(tmp_path, netns):
    ns, host_ip = netns
    hub = f"tcp/{host_ip}:{free_port()}"
    graph = toy_graph(tmp_path, hub, frames=100, delay=0.03, replicas=1)
    out, worker_out = run_with_remote_replica(tmp_path, ns, graph, hub)
    assert frames_done_by(worker_out) > 0, worker_out
    assert_exactly_once(tmp_path, 100)


def secure_graph(tmp_path: Path, host_ip: str, port: int, frames: int, delay: float) -> Path:
    """The toy graph over mutual TLS with access control (`secured`)."""
    return secured(toy_graph(tmp_path, f"tls/{host_ip}:{port}", frames=frames, delay=delay, replicas=1))


def secured(graph: Path) -> Path:
    """`graph` with certificates made by `umad certs` as the README says (bundles in `certs/` beside
    it, the CA in `certs-ca/`): its printed `tls:` and `security:` blocks appended to the graph file."""
    made = run_umad("certs", str(graph), "--out", str(graph.parent / "certs"))
    assert made.returncode == 0, made.stderr
    blocks = yaml.safe_load(made.stdout.partition("\n# for the graph file")[2].partition("\n")[2])
    graph.write_text(yaml.safe_dump({**yaml.safe_load(graph.read_text()), **blocks}, sort_keys=False))
    return graph


def test_hub_requiring_tls_serves_a_remote_worker_with_the_graphs_certificate(tmp_path, netns):
    ns, host_ip = netns
    port = free_port()
    graph = secure_graph(tmp_path, host_ip, port, frames=100, delay=0.03)
    data = yaml.safe_load(graph.read_text())
    data["operators"][0]["params"]["size"] = 1 << 15  # 128 KiB frames: in the source's ring, fetched from afar
    graph.write_text(yaml.safe_dump(data, sort_keys=False))
    # A plain-TCP client gets nothing from a TLS hub.
    plain = remote_worker(ns, graph, "double", 2, f"tcp/{host_ip}:{port}")
    out, worker_out = run_with_remote_replica(tmp_path, ns, graph, f"tls/{host_ip}:{port}")
    plain.send_signal(signal.SIGKILL)
    plain_out, _ = plain.communicate(timeout=30)
    assert frames_done_by(worker_out) > 0, worker_out
    assert "could not be fetched" not in worker_out  # its payload queries pass the hub's rules
    assert "stopped after" not in plain_out
    assert "access control refused" not in out  # the graph's own traffic passes the hub's rules
    assert_exactly_once(tmp_path, 100)
