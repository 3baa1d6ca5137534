"""`umad set OP.PARAM=VALUE ...`: change parameters of a running operator from its next frame on.

Each replica answers with what it did: applied, or refused with the reason (a value the schema
does not accept, a weight file that does not load); the command exits non-zero unless every
replica of every operator named applied its change.
"""

from __future__ import annotations

from umad_common.commands.checks import InputError
from umad_common.commands.common import (
    ANSWER_TIMEOUT_S,
    add_running_graph_arguments,
    connect_to_running_graph,
    report,
)
from umad_common.dataflow.api.assignments import GraphError, parse_sets


def add_arguments(parser):
    parser.add_argument("assignments", nargs="+", metavar="OP.PARAM=VALUE", help="e.g. fusion.weights.ssim=0.5")
    add_running_graph_arguments(parser)


def run(args) -> int:
    from umad_common.dataflow.transport.bus import Keys, ask

    try:
        overrides = parse_sets(args.assignments)
    except GraphError as exc:
        raise InputError("\n".join(exc.problems)) from None
    running = connect_to_running_graph(args)
    if running is None:
        return 1
    keys = Keys(running.name)
    applied = True
    try:
        for op, params in overrides.items():
            answers = ask(running.session, keys.control(op), {"set": params}, ANSWER_TIMEOUT_S)
            for ans in answers:
                if ans["status"] == "applied":
                    ans["message"] = f"{params} (from its next frame on)"
            applied = report(op, answers, running) and applied
    finally:
        running.close()
    return 0 if applied else 1
