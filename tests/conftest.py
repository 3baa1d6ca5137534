"""Shared fixtures: free loopback ports and a way to start `umad` like a user does."""

from __future__ import annotations

import argparse
import os
import random
import shlex
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UMAD = [sys.executable, "-m", "umad_common.cli"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def umad_env() -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


def run_umad(*args: str, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*UMAD, *args], capture_output=True, text=True, timeout=timeout, env=umad_env(), cwd=REPO, **kw
    )


def start_umad(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [*UMAD, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=umad_env(), cwd=REPO
    )


class DrainedUmad:
    """`umad ...` started as a user would, its output read as it comes: a pipe nobody reads fills
    up and stalls the launcher, and with it every operator whose log lines it forwards."""

    def __init__(self, *args: str):
        self.proc = start_umad(*args)
        self.lines: list[str] = []
        self.reader = threading.Thread(target=lambda: self.lines.extend(self.proc.stdout), daemon=True)
        self.reader.start()

    def wait(self, timeout: float) -> str:
        """Wait for the exit; returns everything it printed."""
        self.proc.wait(timeout=timeout)
        self.reader.join(timeout=10)
        return "".join(self.lines)


def readme_recipe(verb: str, command) -> tuple[argparse.Namespace, list[str]]:
    """The README's `umad train VERB ...` line parsed as the CLI parses it (with the command module's
    `add_arguments`), and its words: what the recipe tests compare with a shipped model's record."""
    readme = (REPO / "README.md").read_text().splitlines()
    line = next(line for line in readme if line.startswith(f"umad train {verb} "))
    words = shlex.split(line.split("#")[0])
    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    return parser.parse_args(words[3:]), words


@pytest.fixture
def hub_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def sh(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True)


def namespace_ring_dir(ns: str) -> Path:
    """The other "host"'s own /dev/shm for payload rings (`UMAD_RING_DIR`): a namespace shares this
    host's files, and a worker that mapped the hub host's rings would never fetch a payload."""
    return Path(tempfile.gettempdir()) / f"{ns}-rings"


@pytest.fixture
def netns():
    """A namespace `ns` with address 10.23x.y.2, reaching this host at 10.23x.y.1, and a folder of its
    own for payload rings (`namespace_ring_dir`)."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    tag = f"{os.getpid() % 1000}{random.randint(0, 99)}"
    net = f"10.{231 + random.randint(0, 3)}.{random.randint(1, 250)}"
    ns, host_if, ns_if = f"umad{tag}", f"vu{tag}a", f"vu{tag}b"
    try:
        sh("ip", "netns", "add", ns)
    except (subprocess.CalledProcessError, FileNotFoundError) as exc:
        pytest.skip(f"cannot create a network namespace here: {exc}")
    try:
        sh("ip", "link", "add", host_if, "type", "veth", "peer", "name", ns_if)
        sh("ip", "link", "set", ns_if, "netns", ns)
        sh("ip", "addr", "add", f"{net}.1/24", "dev", host_if)
        sh("ip", "link", "set", host_if, "up")
        sh("ip", "netns", "exec", ns, "ip", "addr", "add", f"{net}.2/24", "dev", ns_if)
        sh("ip", "netns", "exec", ns, "ip", "link", "set", ns_if, "up")
        sh("ip", "netns", "exec", ns, "ip", "link", "set", "lo", "up")
        namespace_ring_dir(ns).mkdir()
        yield ns, f"{net}.1"
    finally:
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        subprocess.run(["ip", "link", "del", host_if], capture_output=True)
        shutil.rmtree(namespace_ring_dir(ns), ignore_errors=True)
