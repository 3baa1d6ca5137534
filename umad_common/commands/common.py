"""Argument helpers the verbs share, and how a command reaches the running graph.

Each argument several verbs take (DATA, `--out`, `--seed`, `--frames`, `--epochs`, `--topics`,
`--device`, the graph file and hub) is declared here once, each verb passing its own default and,
where it means more than the common text says, its own help.

`umad set` and `umad op start|stop` never import an operator: they ask the hub which graph runs
there (the launcher answers with its name, file and operators), then send their command as a query
that the replicas or the launcher answer once they applied or refused it.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from umad_common import DEFAULT_GRAPH
from umad_common.commands.checks import existing_file
from umad_common.dataflow.transport.certificates import CONTROL, add_certificate_arguments

CONNECT_TIMEOUT_S = 10.0  # how long a command waits for the hub's answer once connected
ANSWER_TIMEOUT_S = 30.0  # a replica answers between two frames; only a hung one takes this long


NORMAL_DRIVES_HELP = "drives: a benchmark folder (its normal/ drives are used) or normal drives"
WEIGHTS_FILE_HELP = "weights file (.safetensors); its .json record is written beside it"


def add_data_argument(parser: argparse.ArgumentParser, help: str = NORMAL_DRIVES_HELP) -> None:
    """The positional DATA: the drives a verb reads (default help: a training verb's normal drives)."""
    parser.add_argument("data", type=Path, help=help)


def add_topics_argument(parser: argparse.ArgumentParser) -> None:
    """`--topics`, for every verb that reads drives."""
    parser.add_argument(
        "--topics",
        default=None,
        metavar="ROLE=TOPIC,...",
        help="recordings: the topic of each role, e.g. camera=/a,lidar=/b,odometry=/c,control=/d,labels=/e; "
        "roles not named are chosen by type (`umad data info DATA` shows the choice)",
    )


def add_out_argument(
    parser: argparse.ArgumentParser,
    help: str = WEIGHTS_FILE_HELP,
    required: bool = True,
    default: Path | None = None,
) -> None:
    """`--out PATH`: what the verb writes (default help: a training verb's weights file)."""
    parser.add_argument("--out", type=Path, required=required, default=default, help=help)


def _add_count_argument(
    parser: argparse.ArgumentParser, flag: str, phrase: str, default: int | None, help: str | None
) -> None:
    """An integer `flag`, its help `help`, else `phrase (default N)`."""
    parser.add_argument(flag, type=int, default=default, help=help or f"{phrase} (default {default})")


def add_seed_argument(parser: argparse.ArgumentParser, default: int | None = 0, help: str | None = None) -> None:
    """`--seed N` (default help: `random seed (default N)`)."""
    _add_count_argument(parser, "--seed", "random seed", default, help)


def add_frames_argument(parser: argparse.ArgumentParser, default: int | None, help: str | None = None) -> None:
    """`--frames N` (default help: a training verb's frame budget, spread over its drives)."""
    _add_count_argument(parser, "--frames", "at most this many frames, spread over all scenarios", default, help)


def add_epochs_argument(parser: argparse.ArgumentParser, default: int | None, help: str | None = None) -> None:
    """`--epochs N` (default help: passes over the frames a training verb loaded)."""
    _add_count_argument(parser, "--epochs", "passes over the loaded frames", default, help)


def add_graph_argument(parser: argparse.ArgumentParser, positional: bool = False) -> None:
    if positional:
        parser.add_argument(
            "graph", nargs="?", default=str(DEFAULT_GRAPH), help="graph file (default: the built-in graph.yaml)"
        )
    else:
        parser.add_argument("--graph", default=str(DEFAULT_GRAPH), help="graph file (default: the built-in graph.yaml)")


def add_connect_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--connect", default=None, help="hub endpoint (default: the graph file's `hub`, else the default hub)"
    )


def add_running_graph_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--graph",
        default=None,
        help="graph file: picks the running graph by its name and hub; needed only to start an operator "
        "the running graph's own file does not have (default: whichever graph runs on the hub)",
    )
    add_connect_argument(parser)
    add_certificate_arguments(parser)


@dataclass
class RunningGraph:
    """A session on the hub of a running graph and what its launcher says it runs."""

    session: Any  # zenoh.Session, imported late so `umad --help` stays fast
    name: str
    graph_file: str
    operators: list[str]

    def close(self) -> None:
        self.session.close()


def connect_to_running_graph(args: argparse.Namespace) -> RunningGraph | None:
    """The graph running on the hub (`--connect`, else the `--graph` file's hub, else the default
    one), or None after saying why not: no hub there, it refused our certificate (a TLS graph: the
    `control` one of its `tls.certs`, or `--cert/--key`), no graph on it, or several and none named."""
    from umad_common.dataflow.transport.bus import DEFAULT_HUB, HubJoinError, Keys, ask, open_client

    name, hub, tls = None, DEFAULT_HUB, None
    if args.graph:
        existing_file(Path(args.graph), "--graph", "the graph file of the running graph")
        from umad_common.dataflow.api.graph import graph_address  # reads the file; imports no operator

        name, hub, tls = graph_address(args.graph, CONTROL, args.cert, args.key)
    hub = args.connect or hub
    try:
        session = open_client(hub, tls, timeout_s=CONNECT_TIMEOUT_S, retry=False)
    except HubJoinError as exc:
        print(exc, file=sys.stderr)
        return None
    if session is None:
        print(f"no hub at {hub}: is the graph running (`umad launch`)?", file=sys.stderr)
        return None
    asked = Keys(name).graph_info if name else Keys.ALL_GRAPHS  # a certificate may ask its own graph only
    graphs = {info["name"]: info for info in ask(session, asked, {}, CONNECT_TIMEOUT_S)}
    chosen = graphs.get(name) if name else (next(iter(graphs.values())) if len(graphs) == 1 else None)
    if chosen is None:
        session.close()
        if not graphs and tls is not None:
            print(
                f"no graph answered on the hub at {hub}: none runs there, or the hub's access control refused "
                f"this certificate ({tls.client_cert}); commands need one whose common name has the role control",
                file=sys.stderr,
            )
        elif not graphs:
            print(f"no graph runs on the hub at {hub} (its launcher did not answer)", file=sys.stderr)
        elif name:
            print(f"graph {name!r} does not run on the hub at {hub}; running there: {sorted(graphs)}", file=sys.stderr)
        else:
            print(f"several graphs run on the hub at {hub}: {sorted(graphs)}; pick one with --graph", file=sys.stderr)
        return None
    return RunningGraph(session, chosen["name"], chosen["graph"], chosen["operators"])


def report(target: str, answers: list[dict], running: RunningGraph) -> bool:
    """Print what each replica (or the launcher) answered; True when every answer says applied."""
    if not answers:
        if target in running.operators:
            print(f"{target}: no replica answered within {ANSWER_TIMEOUT_S:.0f}s", file=sys.stderr)
        else:
            ops = ", ".join(running.operators)
            print(f"{target}: no such operator in the running graph {running.name!r} (running: {ops})", file=sys.stderr)
        return False
    applied = True
    for ans in answers:
        who = f"{ans['op']}.{ans['replica']}" if "replica" in ans else target
        detail = ans.get("message") or ans.get("reason") or ""
        line = f"{who}: {ans['status']}" + (f": {detail}" if detail else "")
        if ans["status"] in ("applied", "stopping"):
            print(line)
        else:
            applied = False
            print(line, file=sys.stderr)
    return applied


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    """`--device auto|cpu|cuda[:N]` of a training verb (default auto: CUDA when present)."""
    from umad_common.models.device import DEVICE_HELP, check_device_name

    def device_name(value: str) -> str:
        try:
            return check_device_name(value)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    parser.add_argument(
        "--device",
        type=device_name,
        default="auto",
        help=f"where the model trains: {DEVICE_HELP} (default auto); the weights are saved from the CPU either way",
    )


def resolve_device_or_exit(name: str):
    """The torch device for `--device`, or SystemExit with the reason (e.g. cuda asked, none here)."""
    from umad_common.models.device import resolve_device

    try:
        return resolve_device(name)
    except ValueError as exc:
        raise SystemExit(f"--device: {exc}") from None
