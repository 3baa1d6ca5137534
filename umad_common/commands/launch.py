"""`umad launch [FILE] [--record PATH] [--max-frames N] [--set OP.PARAM=VALUE ...]`."""

from __future__ import annotations

from pathlib import Path

from umad_common.commands.common import add_graph_argument, load_graph_or_exit


def add_arguments(parser):
    add_graph_argument(parser, positional=True)
    parser.add_argument("--record", type=Path, default=None, help="write every bus message to this MCAP file")
    parser.add_argument("--max-frames", type=int, default=None, help="stop the sources after N frames")
    parser.add_argument("--set", action="append", default=[], metavar="OP.PARAM=VALUE", help="override a parameter")
    parser.add_argument("--hub", default=None, help="hub endpoint to listen on (default: the graph's `hub`)")


def run(args) -> int:
    from umad_common.dataflow.launcher import Launcher

    graph = load_graph_or_exit(args.graph, args.set, local=True)
    if graph is None:
        return 1
    return Launcher(graph, Path(args.graph), args.set, args.record, args.max_frames, args.hub).run()
