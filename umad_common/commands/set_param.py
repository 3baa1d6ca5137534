"""`umad set OP.PARAM=VALUE ...`: change parameters of a running operator from its next frame on."""

from __future__ import annotations

import json
import sys
import time

from umad_common.commands.common import add_graph_argument, load_graph_or_exit, parse_sets
from umad_common.graph import GraphError


def add_arguments(parser):
    parser.add_argument("assignments", nargs="+", metavar="OP.PARAM=VALUE", help="e.g. fusion.weights.ssim=0.5")
    add_graph_argument(parser)
    parser.add_argument("--connect", default=None, help="hub endpoint (default: the graph's `hub`)")


def run(args) -> int:
    from umad_common.bus import Keys, open_client

    graph = load_graph_or_exit(args.graph)
    if graph is None:
        return 1
    try:
        overrides = parse_sets(args.assignments)
        graph.with_params(overrides)  # validate against each operator's schema before sending
    except GraphError as exc:
        print(exc, file=sys.stderr)
        return 1
    session = open_client(args.connect or graph.spec.hub)
    try:
        time.sleep(0.3)
        for op, params in overrides.items():
            session.put(Keys(graph.name).control(op), json.dumps({"set": params}))
            print(f"{op}: {params}")
        time.sleep(0.3)
    finally:
        session.close()
    return 0
