"""`umad op run ID [--graph FILE] [--connect tcp/HOST:PORT]`: one operator joining a running graph."""

from __future__ import annotations

import sys

from umad_common.commands.common import add_connect_argument, add_graph_argument, load_graph_or_exit
from umad_common.dataflow.assignments import GraphError
from umad_common.dataflow.certificates import add_certificate_arguments


def add_arguments(parser):
    parser.add_argument("id", help="operator id in the graph")
    add_graph_argument(parser)
    add_connect_argument(parser)
    parser.add_argument("--replica", type=int, default=0, help="replica index (distinct per process of one operator)")
    parser.add_argument("--set", action="append", default=[], metavar="OP.PARAM=VALUE")
    add_certificate_arguments(parser)


def run(args) -> int:
    from umad_common.dataflow.runtime import run_operator

    graph = load_graph_or_exit(args.graph, args.set)
    if graph is None:
        return 1
    try:
        graph.op(args.id)
    except GraphError as exc:
        print(exc, file=sys.stderr)
        return 1
    run_operator(graph, args.id, args.replica, args.connect, cert=args.cert, key=args.key)  # ends the process
