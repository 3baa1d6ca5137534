"""`umad launch [FILE | --live] [--record PATH] [--max-frames N] [--set OP.PARAM=VALUE ...]`."""

from __future__ import annotations

from pathlib import Path

from umad_common import DEFAULT_GRAPH, LIVE_GRAPH
from umad_common.commands.checks import (
    InputError,
    checked_graph,
    free_hub_port,
    lidar_notice,
    print_notice,
    print_open_access_warning,
    source_drives,
    tls_hub,
    writable_output,
)
from umad_common.commands.common import add_graph_argument


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
    if args.live and args.graph != str(DEFAULT_GRAPH):
        raise InputError.of(
            f"--live and {args.graph}", "both given", "either a graph file or --live (the shipped live graph)"
        )
    path = str(LIVE_GRAPH) if args.live else args.graph
    graph = checked_graph(path, args.set, local=True, runs=True)
    print_notice(lidar_notice(graph, source_drives(graph), "the replayer's drives"))
    if args.hub:
        tls_hub(args.hub, "--hub", graph)
    print_open_access_warning(graph, path)
    free_hub_port(args.hub or graph.spec.hub, "--hub" if args.hub else f"{path}: hub")
    if args.record:
        writable_output(args.record, "--record", folder=False)

    from umad_common.dataflow.launch.launcher import Launcher

    return Launcher(
        graph, Path(path), sets=args.set, record=args.record, max_frames=args.max_frames, hub=args.hub
    ).run()
