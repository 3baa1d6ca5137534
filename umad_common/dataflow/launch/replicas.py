"""One replica as the launcher sees it: its command line, its process and its restarts, and what
its process has cost."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

from umad_common.dataflow.api.graph import Graph, OperatorSpec

OPERATOR_NICENESS = 5  # operators yield the CPU to the hub and the launcher (the control path)


@dataclass(kw_only=True)
class Replica:
    op_id: str
    index: int
    command: list[str]
    is_source: bool
    proc: subprocess.Popen | None = None
    restarts: int = 0
    restart_at: float | None = None
    started_at: float = 0.0
    finished: bool = False
    failed: bool = False
    readers: list[threading.Thread] = field(default_factory=list)

    @property
    def name(self) -> str:
        return f"{self.op_id}.{self.index}"


def replica_command(
    graph: Graph, graph_file: Path, spec: OperatorSpec, index: int, *, hub: str, sets: list[str]
) -> list[str]:
    """The command line of one replica, in the operator's own Python environment if it names one."""
    python = spec.python or sys.executable
    if spec.python and not Path(spec.python).is_absolute():
        python = str(graph.base_dir / spec.python)
    cmd = [
        python,
        "-m",
        "umad_common.dataflow.process.replica",
        "--graph",
        str(graph_file),
        "--op",
        spec.id,
        "--replica",
        str(index),
        "--connect",
        hub,
    ]
    for text in sets:  # every process sees the whole effective graph (e.g. a source's pacing)
        cmd += ["--set", text]
    return cmd


def process_cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system) process `pid` has used so far; None where /proc cannot say."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime: fields 14, 15
