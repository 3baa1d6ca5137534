"""Shared fixtures: free loopback ports and a way to start `umad` like a user does."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
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


@pytest.fixture
def hub_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"
