"""`umad set OP.PARAM=VALUE ...`: change parameters of a running operator from its next frame on."""

from __future__ import annotations

import json
import sys
import time

from umad_common.commands.common import (
    add_connect_argument,
    add_graph_argument,
    connect_to_running_graph,
    load_graph_or_exit,
    parse_sets,
)
from umad_common.graph import GraphError


def add_arguments(parser):
    parser.add_argument("assignments", nargs="+", metavar="OP.PARAM=VALUE", help="e.g. fusion.weights.ssim=0.5")
    add_graph_argument(parser)
    add_connect_argument(parser)


def run(args) -> int:
    from umad_common.bus import Keys

    graph = load_graph_or_exit(args.graph)
    if graph is None:
        return 1
    try:
        overrides = parse_sets(args.assignments)
        graph.with_params(overrides)  # validate against each operator's schema before sending
    except GraphError as exc:
        print(exc, file=sys.stderr)
        return 1
    connected = connect_to_running_graph(graph, args.connect, wanted=set(overrides))
    if connected is None:
        return 1
    session, live = connected
    keys = Keys(graph.name)
    missing = []
    try:
        for op, params in overrides.items():
            if op not in live:
                missing.append(op)
                print(f"{op}: no live replica in graph {graph.name!r}; not changed", file=sys.stderr)
                continue
            session.put(keys.control(op), json.dumps({"set": params}))
            print(f"{op}: {params} (from its next frame on)")
        time.sleep(0.3)
    finally:
        session.close()
    return 1 if missing else 0
