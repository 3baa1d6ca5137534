"""One process runs one replica of one operator: connect to the hub, run the replica until its
stream ends (sources) or a signal arrives, and end the process (`python -m
umad_common.dataflow.process.replica`, what the launcher starts for every replica)."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from typing import NoReturn

from threadpoolctl import threadpool_limits

from umad_common.dataflow.api.assignments import GraphError, parse_sets
from umad_common.dataflow.api.exit_codes import EXIT_CONFIG
from umad_common.dataflow.api.graph import Graph, load_graph
from umad_common.dataflow.process.allocator import keep_freed_memory
from umad_common.dataflow.process.runtime import OperatorRuntime
from umad_common.dataflow.record.mcap_log import LogError
from umad_common.dataflow.transport.bus import HubJoinError, ShutdownSignal, close_session, open_client
from umad_common.dataflow.transport.certificates import add_certificate_arguments, operator_identity
from umad_common.dataflow.transport.planes import on_this_host

log = logging.getLogger("umad.runtime")


def run_operator(
    graph: Graph,
    op_id: str,
    *,
    replica: int = 0,
    connect: str | None = None,
    max_frames: int | None = None,
    replay_log: str | None = None,
    allow_truncated: bool = False,
    cert: str | None = None,
    key: str | None = None,
) -> NoReturn:
    """Connect to the hub, run one replica until the stream ends (sources) or a signal arrives, and
    end the process. With TLS it presents `cert`/`key`, else its operator's certificate `op-<id>` of
    the graph's `tls.certs`; a hub that refuses it ends the process with one line saying so.

    The process ends with `os._exit` once its operator and session are closed and its output is
    flushed. The interpreter's own finalization is skipped: it garbage-collects every object torch,
    scikit-learn and the models left behind, CPU that a graph stopping all its replicas at once on
    a busy machine does not have (replicas through their own shutdown soon after SIGTERM sat in that
    collection past the launcher's grace period and were killed: docs/experiments.md). With the hub
    gone, Zenoh's threads would hold up a normal exit as well.
    """
    one_blas_thread()
    keep_freed_memory()
    shutdown = ShutdownSignal()
    tls = graph.tls_config(operator_identity(op_id), cert, key)
    hub = connect or graph.spec.hub
    hub_on_this_host = on_this_host(hub)
    try:
        session = open_client(
            hub,
            tls,
            cancel=shutdown.event,
            shm_pool_mib=graph.spec.shm_pool_mib,
            direct_links=hub_on_this_host and graph.spec.direct_links and tls is None,
        )
    except HubJoinError as exc:
        log.error("operator %s could not join: %s", op_id, exc)
        _exit(EXIT_CONFIG)
    if session is None:
        log.info("stopped while waiting for the hub at %s", hub)
        _exit(0)
    code = 0
    try:
        runtime = OperatorRuntime(
            graph=graph,
            op_id=op_id,
            replica=replica,
            session=session,
            shutdown=shutdown.event,
            max_frames=max_frames,
            replay_log=replay_log,
            allow_truncated=allow_truncated,
            hub_on_this_host=hub_on_this_host,
        )
    except Exception as exc:  # bad parameters, missing weights: say so once, do not restart
        log.error("operator %s could not start: %s: %s", op_id, type(exc).__name__, exc)
        code = EXIT_CONFIG
    else:
        try:
            runtime.run()
        except LogError as exc:
            log.error("%s", exc)
            code = EXIT_CONFIG
        finally:
            runtime.operator.close()
    finally:
        close_session(session)
    _exit(code)


def one_blas_thread() -> threadpool_limits:
    """Limit numpy's BLAS to one thread in this process (until the returned limiter, used as a context
    manager, exits).

    By default BLAS starts a thread per core that spins after every call: in a mask refiner that
    spinning cost many times the CPU of its own work (docs/experiments.md). A replica's parallelism
    is the graph's processes; an operator that wants threads for its own work (torch's `threads`) sets them."""
    return threadpool_limits(limits=1, user_api="blas")


def _exit(code: int) -> NoReturn:
    """End the process at once, after flushing what it has to say."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Run one operator replica of a UMAD graph.")
    parser.add_argument("--graph", required=True)
    parser.add_argument("--op", required=True)
    parser.add_argument("--replica", type=int, default=0)
    parser.add_argument("--connect", default=None, help="hub endpoint, default: the graph's `hub`")
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="OP.PARAM=VALUE")
    parser.add_argument("--replay-log", default=None, help="sources publish this MCAP log's recorded frames")
    parser.add_argument("--allow-truncated", action="store_true")
    add_certificate_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        graph = load_graph(args.graph)
        overrides = parse_sets(args.set)
        if overrides:
            graph = graph.with_params(overrides)
    except GraphError as exc:
        print(exc, file=sys.stderr)
        return EXIT_CONFIG
    run_operator(
        graph,
        args.op,
        replica=args.replica,
        connect=args.connect,
        max_frames=args.max_frames,
        replay_log=args.replay_log,
        allow_truncated=args.allow_truncated,
        cert=args.cert,
        key=args.key,
    )


if __name__ == "__main__":
    sys.exit(main())
