"""`umad op run ID [--graph FILE] [--connect tcp/HOST:PORT]`: one operator joining a running graph."""

from __future__ import annotations

from umad_common.commands.checks import InputError, checked_graph
from umad_common.commands.common import add_connect_argument, add_graph_argument
from umad_common.dataflow.transport.certificates import add_certificate_arguments


def add_arguments(parser):
    parser.add_argument("id", help="operator id in the graph")
    add_graph_argument(parser)
    add_connect_argument(parser)
    parser.add_argument("--replica", type=int, default=0, help="replica index (distinct per process of one operator)")
    parser.add_argument("--set", action="append", default=[], metavar="OP.PARAM=VALUE")
    add_certificate_arguments(parser)


def run(args) -> int:
    graph = checked_graph(args.graph, args.set)
    if args.id not in {op.id for op in graph.spec.operators}:
        ids = ", ".join(op.id for op in graph.spec.operators)
        raise InputError.of(f"operator {args.id!r}", f"not in the graph {args.graph}", f"one of its operators: {ids}")

    from umad_common.dataflow.process.replica import run_operator

    run_operator(
        graph, args.id, replica=args.replica, connect=args.connect, cert=args.cert, key=args.key
    )  # ends the process
