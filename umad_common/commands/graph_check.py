"""`umad graph check [FILE]`: validate a graph without starting anything."""

from __future__ import annotations

from umad_common.commands.common import add_graph_argument, load_graph_or_exit


def add_arguments(parser):
    add_graph_argument(parser, positional=True)


def run(args) -> int:
    graph = load_graph_or_exit(args.graph, local=True)
    if graph is None:
        return 1
    ops = graph.spec.operators
    print(
        f"{args.graph}: ok ({len(ops)} operators, {sum(o.replicas for o in ops)} processes; sources {graph.sources()}, sinks {graph.sinks()})"
    )
    return 0
