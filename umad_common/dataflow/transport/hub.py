"""The hub: a router-mode Zenoh session in a process of its own, so the launcher can restart it.

Clients reconnect to a restarted hub by themselves; frames lost meanwhile are re-sent by the
sources' retransmission, so a hub restart costs time, not frames.

With access control (a graph's `security:`), every message the hub refuses is logged with the
certificate's common name, the message kind and the key. Zenoh writes its decisions only as trace
lines on its standard output, one per message, allowed ones included, so the hub reads its own
standard output through a pipe and keeps the refusals.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
import threading
import time
from pathlib import Path

import zenoh

from umad_common.dataflow.transport.bus import ShutdownSignal, TlsConfig, open_hub

ACL_LOG_TARGET = "zenoh::net::routing::interceptor::access_control"
REPEAT_LOG_INTERVAL_S = 10.0  # a refusal that repeats is logged again at most this often, with its count
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_DECISION = re.compile(
    r"ThreadId\((?P<thread>\d+)\).*: (?P<cached>Using cached result: )?(?P<zid>[0-9a-f]+) (?:on (?P<subject>\S+) )?"
    r"is (?P<verdict>un)?authorized to (?P<action>.+) \((?P<flow>ingress|egress)\) on (?P<key>\S+)"
)
_COMMON_NAME = re.compile(r"CertCommonName\((?P<name>[^)]*)\)")
_CACHING = re.compile(
    r"ThreadId\((?P<thread>\d+)\).*ACL \((?P<flow>ingress|egress)\): caching permissions for `(?P<key>[^`]*)`"
)
log = logging.getLogger("umad.hub")


class RefusalLog:
    """Turns Zenoh's access-control trace lines into one log line per refusal.

    When Zenoh first meets a key it caches its permissions and prints one line per message kind for
    it, allowed or not, though nothing was sent; those lines follow a `caching permissions for
    `KEY`` line on the same thread, each kind once, and are skipped. They name the session's
    certificate, which later decisions from that cache (`Using cached result: ZID ...`) do not, so
    the names are kept by Zenoh session id. A refusal that repeats (a process publishing where it may
    not, frame after frame) is logged once, then with its count at most every REPEAT_LOG_INTERVAL_S."""

    def __init__(self, out) -> None:
        self.out = out  # where the hub's other standard output goes
        self._caching: dict[str, tuple[str, str, set[str]]] = {}  # thread -> (flow, key, kinds seen)
        self._repeats: dict[tuple[str, str, str, str], list[float]] = {}  # refusal -> [count since logged, when]
        self._names: dict[str, str] = {}  # Zenoh session id -> its certificate's common name

    def line(self, text: str) -> None:
        plain = _ANSI.sub("", text)
        cached = _CACHING.search(plain)
        if cached:
            self._caching[cached["thread"]] = (cached["flow"], cached["key"], set())
            return
        decision = _DECISION.search(plain)
        if decision is None:
            if ACL_LOG_TARGET not in plain:
                self.out.write(text)
                self.out.flush()
            return
        named = _COMMON_NAME.search(decision["subject"] or "")
        if named:
            self._names[decision["zid"]] = named["name"]
        block = self._caching.get(decision["thread"])
        in_block = block and not decision["cached"] and block[:2] == (decision["flow"], decision["key"])
        if in_block and decision["action"] not in block[2]:
            block[2].add(decision["action"])
            return
        self._caching.pop(decision["thread"], None)
        if decision["verdict"]:
            name = self._names.get(decision["zid"], f"session {decision['zid']} (no certificate name)")
            self._refused(name, decision["action"], decision["flow"], decision["key"])

    def _refused(self, name: str, action: str, flow: str, key: str) -> None:
        refusal = (name, action, flow, key)
        now = time.monotonic()
        seen = self._repeats.get(refusal)
        if seen is None:
            self._repeats[refusal] = [0, now]
            log.warning("access control refused %s: %s (%s) on %s", name, action, flow, key)
            return
        seen[0] += 1
        if now - seen[1] >= REPEAT_LOG_INTERVAL_S:
            log.warning("access control refused %s: %s (%s) on %s, %d more times", name, action, flow, key, seen[0])
            self._repeats[refusal] = [0, now]


def read_refusals_from_stdout() -> None:
    """Route this process's standard output (Zenoh's log included) through a RefusalLog thread."""
    read_end, write_end = os.pipe()
    out = os.fdopen(os.dup(1), "w")
    os.dup2(write_end, 1)
    os.close(write_end)
    sys.stdout = os.fdopen(1, "w", buffering=1)
    refusals = RefusalLog(out)

    def pump() -> None:
        with os.fdopen(read_end, errors="replace") as lines:
            for text in lines:
                refusals.line(text)

    threading.Thread(target=pump, daemon=True).start()
    rust_log = os.environ.get("RUST_LOG", "error")
    os.environ["RUST_LOG"] = f"{rust_log},{ACL_LOG_TARGET}=trace"
    zenoh.init_log_from_env_or("error")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Run the UMAD hub (Zenoh router).")
    parser.add_argument("--listen", required=True, help="endpoint, e.g. tcp/127.0.0.1:7447 or tls/0.0.0.0:7447")
    parser.add_argument("--root-ca", default=None)
    parser.add_argument("--cert", default=None)
    parser.add_argument("--key", default=None)
    parser.add_argument(
        "--access-control", default=None, help="file of Zenoh's access_control as JSON (the launcher's, mode 0600)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    shutdown = ShutdownSignal()
    tls = TlsConfig(args.root_ca, args.cert, args.key) if args.cert else None
    access_control = json.loads(Path(args.access_control).read_text()) if args.access_control else None
    if access_control is not None:
        read_refusals_from_stdout()
    session = open_hub(args.listen, tls, access_control)
    try:
        print(f"hub listening on {args.listen}", flush=True)
        shutdown.event.wait()
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
