"""Argument helpers the graph-running verbs share."""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

from umad_common.graph import Graph, GraphError, load_graph, missing_local_files, parse_assignment

DEFAULT_GRAPH = Path(__file__).resolve().parents[2] / "graph.yaml"
CONNECT_TIMEOUT_S = 10.0  # how long `umad set` / `umad op` wait for a running graph's hub
LIVELINESS_ATTEMPTS = 3


def add_graph_argument(parser: argparse.ArgumentParser, positional: bool = False) -> None:
    if positional:
        parser.add_argument(
            "graph", nargs="?", default=str(DEFAULT_GRAPH), help="graph file (default: the built-in graph.yaml)"
        )
    else:
        parser.add_argument("--graph", default=str(DEFAULT_GRAPH), help="graph file (default: the built-in graph.yaml)")


def parse_sets(sets: list[str]) -> dict[str, dict[str, Any]]:
    overrides: dict[str, dict[str, Any]] = defaultdict(dict)
    for text in sets:
        op, param, value = parse_assignment(text)
        overrides[op][param] = value
    return dict(overrides)


def load_graph_or_exit(path: str, sets: list[str] | None = None, local: bool = False) -> Graph | None:
    """The validated graph with `--set` overrides applied, or None after printing every problem.
    `local`: the whole graph runs here, so also check the interpreters and TLS files it names."""
    try:
        graph = load_graph(path)
        overrides = parse_sets(sets or [])
        graph = graph.with_params(overrides) if overrides else graph
        problems = missing_local_files(graph) if local else []
        if problems:
            raise GraphError([f"{path}: {p}" for p in problems])
        return graph
    except GraphError as exc:
        print(exc, file=sys.stderr)
        return None


def add_connect_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--connect", default=None, help="hub endpoint (default: the graph's `hub`)")


def connect_to_running_graph(graph: Graph, connect: str | None, wanted: set[str] | None = None):
    """A session on the running graph's hub and the operators live there, or None after saying that
    no hub answered: commands to a graph that is not running must fail fast, not hang. Liveliness
    replies right after connecting can be incomplete, so a missing `wanted` operator is asked for
    again before it counts as absent."""
    from umad_common.bus import Keys, live_replicas, open_client

    hub = connect or graph.spec.hub
    session = open_client(hub, graph.tls_config(), timeout_s=CONNECT_TIMEOUT_S)
    if session is None:
        print(
            f"no hub at {hub} within {CONNECT_TIMEOUT_S:.0f}s: is the graph running (`umad launch`)?", file=sys.stderr
        )
        return None
    live: set[str] = set()
    for attempt in range(LIVELINESS_ATTEMPTS):
        time.sleep(0.3 * (attempt + 1))
        live |= {op for op, _ in live_replicas(session, Keys(graph.name))}
        if live and (wanted is None or wanted <= live):
            break
    return session, live
