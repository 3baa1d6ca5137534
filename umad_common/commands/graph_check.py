"""`umad graph check [FILE]`: validate a graph without starting anything."""

from __future__ import annotations

from umad_common.commands.checks import checked_graph, print_open_access_warning
from umad_common.commands.common import add_graph_argument


def add_arguments(parser):
    add_graph_argument(parser, positional=True)


def run(args) -> int:
    graph = checked_graph(args.graph, local=True)
    print_open_access_warning(graph, args.graph)
    ops = graph.spec.operators
    print(
        f"{args.graph}: ok ({len(ops)} operators, {sum(o.replicas for o in ops)} processes; sources {graph.sources()}, sinks {graph.sinks()})"
    )
    return 0
