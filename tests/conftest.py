"""Shared fixtures: free loopback ports and a way to start `umad` like a user does."""

from __future__ import annotations

import argparse
import os
import shlex
import socket
import subprocess
import sys
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
