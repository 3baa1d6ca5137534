"""Argument helpers the graph-running verbs share."""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

from umad_common.graph import Graph, GraphError, load_graph, parse_assignment

DEFAULT_GRAPH = Path(__file__).resolve().parents[2] / "graph.yaml"


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


def load_graph_or_exit(path: str, sets: list[str] | None = None) -> Graph | None:
    """The validated graph with `--set` overrides applied, or None after printing every problem."""
    try:
        graph = load_graph(path)
        overrides = parse_sets(sets or [])
        return graph.with_params(overrides) if overrides else graph
    except GraphError as exc:
        print(exc, file=sys.stderr)
        return None
