"""`umad launch [FILE | --live] [--record PATH] [--max-frames N] [--set OP.PARAM=VALUE ...]`."""

from __future__ import annotations

import sys
from pathlib import Path

from umad_common import DEFAULT_GRAPH, LIVE_GRAPH
from umad_common.commands.common import add_graph_argument, load_graph_or_exit


def add_arguments(parser):
    add_graph_argument(parser, positional=True)
    parser.add_argument(
        "--live",
        action="store_true",
        help="launch the shipped live graph instead (UMAD alone, the replayer at 10 Hz, a per-frame result: "
        "umad_common/graphs/live.yaml); its drives: --set replayer.source=DIR",
    )
    parser.add_argument("--record", type=Path, default=None, help="write every bus message to this MCAP file")
    parser.add_argument("--max-frames", type=int, default=None, help="stop the sources after N frames")
    parser.add_argument("--set", action="append", default=[], metavar="OP.PARAM=VALUE", help="override a parameter")
    parser.add_argument("--hub", default=None, help="hub endpoint to listen on (default: the graph's `hub`)")


def run(args) -> int:
    from umad_common.dataflow.launcher import Launcher

    if args.live and args.graph != str(DEFAULT_GRAPH):
        print(f"umad launch: give either a graph file ({args.graph}) or --live, not both", file=sys.stderr)
        return 1
    path = str(LIVE_GRAPH) if args.live else args.graph
    graph = load_graph_or_exit(path, args.set, local=True)
    if graph is None:
        return 1
    return Launcher(graph, Path(path), args.set, args.record, args.max_frames, args.hub).run()
