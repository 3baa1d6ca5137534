"""`umad replay PATH [--graph FILE] [--record PATH2] [--rate realtime|max]`.

Runs the graph with its sources publishing the log's recorded payloads byte for byte, so every
downstream output is bit-identical to the recorded run. Without --graph, the graph stored in the
log is used.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import yaml

from umad_common.commands.checks import InputError, checked_graph, free_hub_port, recorded_log, writable_output


def add_arguments(parser):
    parser.add_argument("log", type=Path, help="MCAP log written by `umad launch --record`")
    parser.add_argument("--graph", default=None, help="graph file (default: the one stored in the log)")
    parser.add_argument("--record", type=Path, default=None, help="record the replayed run to this MCAP file")
    parser.add_argument(
        "--rate",
        choices=["realtime", "max"],
        default="max",
        help="realtime: 10 Hz; max: lossless, as fast as acks allow",
    )
    parser.add_argument("--allow-truncated", action="store_true", help="replay the readable part of a truncated log")
    parser.add_argument("--set", action="append", default=[], metavar="OP.PARAM=VALUE")


def run(args) -> int:
    recorded_log(args.log, "log")
    if args.record:
        writable_output(args.record, "--record", folder=False)

    from umad_common.dataflow.record.mcap_log import LogError, read_log, read_metadata

    graph_path = args.graph
    sets = list(args.set)
    if graph_path is None:
        metadata = read_metadata(args.log)
        sets = json.loads(metadata.get("sets") or "[]") + sets  # the recorded run's overrides, then these
        text = metadata.get("graph")
        if not text:
            raise InputError.of(f"log {args.log}", "stores no graph", "--graph FILE naming the graph to replay it with")
        data = yaml.safe_load(text)
        data.setdefault("base_dir", metadata.get("base_dir") or str(Path.cwd()))
        tmp = Path(tempfile.mkdtemp(prefix="umad-replay-")) / "graph.yaml"
        tmp.write_text(yaml.safe_dump(data, sort_keys=False))
        graph_path = str(tmp)
        print(f"using the graph stored in the log ({tmp})")
    graph = checked_graph(graph_path, sets, local=True)
    free_hub_port(graph.spec.hub, f"{graph_path}: hub")

    from umad_common.dataflow.launch.launcher import Launcher

    try:
        count = sum(1 for _ in read_log(args.log, allow_truncated=args.allow_truncated))
    except LogError as exc:
        print(exc, file=sys.stderr)
        return 1
    if args.rate == "realtime":
        sets += [f"{src}.pacing=realtime" for src in graph.sources()]
    print(f"{args.log}: {count} messages")
    return Launcher(
        graph,
        Path(graph_path),
        sets=sets,
        record=args.record,
        replay_log=args.log,
        allow_truncated=args.allow_truncated,
    ).run()
