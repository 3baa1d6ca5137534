"""`umad op start ID` / `umad op stop ID`: change which operators a running graph has.

Both talk to the launcher over its control key; `start` re-reads the graph file, so an operator added
to the file after launch can be started (hot swap). Fusion and other wildcard consumers use a new
producer from the next complete frame on.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from umad_common.commands.common import (
    add_connect_argument,
    add_graph_argument,
    connect_to_running_graph,
    load_graph_or_exit,
)


def add_arguments(parser):
    parser.add_argument("id", help="operator id in the graph file")
    add_graph_argument(parser)
    add_connect_argument(parser)


def run(args) -> int:
    from umad_common.bus import Keys

    graph = load_graph_or_exit(args.graph)
    if graph is None:
        return 1
    action = args._words[1]
    if action == "start" and args.id not in {o.id for o in graph.spec.operators}:
        print(f"{args.graph}: no operator {args.id!r} to start", file=sys.stderr)
        return 1
    connected = connect_to_running_graph(graph, args.connect, wanted={args.id} if action == "stop" else None)
    if connected is None:
        return 1
    session, live = connected
    try:
        if not live:
            print(f"no operator of graph {graph.name!r} is live: nothing to {action}", file=sys.stderr)
            return 1
        if action == "stop" and args.id not in live:
            print(f"{args.id}: not running in graph {graph.name!r} (live: {sorted(live)})", file=sys.stderr)
            return 1
        graph_file = str(Path(args.graph).resolve())  # the launcher may run in another folder
        session.put(Keys(graph.name).control("_launcher"), json.dumps({action: args.id, "graph": graph_file}))
        time.sleep(0.3)
    finally:
        session.close()
    print(f"asked the launcher to {action} {args.id}")
    return 0
