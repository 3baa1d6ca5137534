"""`umad op start ID` / `umad op stop ID`: change which operators a running graph has.

Both ask the launcher of the graph running on the hub, which answers with what it did. `start`
reads the launched graph file again, so an operator added to it after launch can be started (hot
swap); `--graph FILE` starts an operator from another file. Fusion and other wildcard consumers use
a new producer from the next complete frame on.
"""

from __future__ import annotations

import sys
from pathlib import Path

from umad_common.commands.common import (
    ANSWER_TIMEOUT_S,
    add_running_graph_arguments,
    connect_to_running_graph,
    report,
)


def add_arguments(parser):
    parser.add_argument("id", help="operator id")
    add_running_graph_arguments(parser)


def run(args) -> int:
    from umad_common.dataflow.transport.bus import Keys, ask

    action = args._words[1]
    running = connect_to_running_graph(args)
    if running is None:
        return 1
    command = {action: args.id}
    if action == "start" and args.graph:
        command["graph"] = str(Path(args.graph).resolve())  # the launcher may run in another folder
    try:
        answers = ask(running.session, Keys(running.name).launcher, command, ANSWER_TIMEOUT_S)
    finally:
        running.close()
    if not answers:
        print(f"the launcher of graph {running.name!r} did not answer within {ANSWER_TIMEOUT_S:.0f}s", file=sys.stderr)
        return 1
    return 0 if report(args.id, answers, running) else 1
