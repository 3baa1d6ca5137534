"""`umad op start ID` / `umad op stop ID`: change which operators a running graph has.

Both talk to the launcher over its control key; `start` re-reads the graph file, so an operator added
to the file after launch can be started (hot swap). Fusion and other wildcard consumers use a new
producer from the next complete frame on.
"""

from __future__ import annotations

import json
import time

from umad_common.commands.common import add_graph_argument, load_graph_or_exit


def add_arguments(parser):
    parser.add_argument("id", help="operator id in the graph file")
    add_graph_argument(parser)
    parser.add_argument("--connect", default=None, help="hub endpoint (default: the graph's `hub`)")


def run(args) -> int:
    from umad_common.bus import Keys, open_client

    graph = load_graph_or_exit(args.graph)
    if graph is None:
        return 1
    action = args._words[1]
    if action == "start" and args.id not in {o.id for o in graph.spec.operators}:
        print(f"{args.graph}: no operator {args.id!r} to start")
        return 1
    session = open_client(args.connect or graph.spec.hub)
    try:
        time.sleep(0.3)
        session.put(Keys(graph.name).control("_launcher"), json.dumps({action: args.id, "graph": str(args.graph)}))
        time.sleep(0.3)
    finally:
        session.close()
    print(f"asked the launcher to {action} {args.id}")
    return 0
