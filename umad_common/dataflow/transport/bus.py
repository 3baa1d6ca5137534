"""Zenoh plumbing in one place: session configs, key names, shutdown signals, shared-memory hygiene.

Topology: the launcher opens a router-mode session (the hub). A replica on the hub's host opens a
peer session that connects to the hub and links directly to the other peers it learns of there
(`direct_links`); a replica on another host opens a client session, so it only needs the hub's
endpoint. Multicast scouting is off everywhere.

Commands (`umad set`, `umad op`) are Zenoh queries: every replica or the launcher that receives one
answers with what it did, so a command always hears back. They travel at a higher priority than
the frames, so a hub queue full of frames does not hold them up.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh

from umad_common.dataflow.transport.planes.ring import remove_stale_rings

DEFAULT_HUB = "tcp/127.0.0.1:7447"
DIRECT_LINK_LISTEN = "tcp/127.0.0.1:0"  # a peer replica's own endpoint for its direct links (any free port)
CONTROL_PRIORITY = zenoh.Priority.INTERACTIVE_HIGH  # commands and their answers overtake queued frames
SHM_DIR = Path("/dev/shm")
log = logging.getLogger("umad.bus")


@dataclass(frozen=True)
class TlsConfig:
    """Zenoh mutual TLS: the hub listens on `tls/...` with `cert`; each side checks that the other's
    certificate is signed by `root_ca`, so a client presents `client_cert` (none: the hub refuses it)."""

    root_ca: str
    cert: str
    key: str
    client_cert: str | None = None
    client_key: str | None = None


class HubJoinError(ConnectionError):
    """This process cannot join a TLS hub: a certificate file of its own is missing, or the hub's port
    answers but the handshake fails (a certificate one side does not accept)."""


def zenoh_config(
    mode: str,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    tls: TlsConfig | None = None,
    shared_memory: bool = True,
    retry: bool = True,
    shm_pool_mib: int | None = None,
    access_control: dict | None = None,
) -> zenoh.Config:
    """The one place every Zenoh config is built. `retry=False`: a client that finds no hub fails
    at once instead of waiting for one (a command to a graph that is not running). `shm_pool_mib`:
    the session's shared-memory pool for large messages (Zenoh's default: 16 MiB); a message that
    finds no room in it goes through the hub's socket. `access_control`: the hub's Zenoh ACL
    (`umad_common.dataflow.launch.access`)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if not shared_memory:
        conf.insert_json5("transport/shared_memory/enabled", "false")
    if shm_pool_mib is not None:
        conf.insert_json5("transport/shared_memory/transport_optimization/pool_size", str(shm_pool_mib << 20))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        if retry:  # clients keep retrying the hub, so a restarted hub is rejoined
            conf.insert_json5("connect/timeout_ms", "-1")
    if tls is not None:
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(tls.root_ca))
        conf.insert_json5("transport/link/tls/enable_mtls", "true")
        if mode == "router":
            conf.insert_json5("transport/link/tls/listen_certificate", json.dumps(tls.cert))
            conf.insert_json5("transport/link/tls/listen_private_key", json.dumps(tls.key))
        elif tls.client_cert and tls.client_key:
            conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(tls.client_cert))
            conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(tls.client_key))
    if access_control is not None:
        conf.insert_json5("access_control", json.dumps(access_control))
    return conf


def open_hub(
    endpoint: str = DEFAULT_HUB, tls: TlsConfig | None = None, access_control: dict | None = None
) -> zenoh.Session:
    """A router-mode session listening on `endpoint`, enforcing `access_control` where given."""
    return zenoh.open(zenoh_config("router", listen=[endpoint], tls=tls, access_control=access_control))


def _port_answers(endpoint: str) -> bool:
    """Whether something accepts TCP connections at `proto/HOST:PORT`."""
    host, _, port = endpoint.partition("/")[2].rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=2.0):
            return True
    except (OSError, ValueError):
        return False


def check_tls_handshake(endpoint: str, tls: TlsConfig) -> None:
    """Raise HubJoinError where a certificate file of ours is missing, or the hub at `endpoint`
    listens but the TLS handshake fails; return where it succeeds or nothing listens yet (the caller
    waits for the hub then). Zenoh's own error does not say why, and a client that keeps retrying a
    hub that refuses it would wait for ever."""
    for what, path in (("CA certificate", tls.root_ca), ("certificate", tls.client_cert), ("key", tls.client_key)):
        if path and not Path(path).is_file():
            raise HubJoinError(f"this process's {what} {path} for the hub at {endpoint} is not a file")
    try:
        probe = zenoh.open(zenoh_config("client", connect=[endpoint], tls=tls, shared_memory=False, retry=False))
    except zenoh.ZError:
        if _port_answers(endpoint):
            own = tls.client_cert or "no certificate (give --cert/--key, or tls.certs in the graph)"
            raise HubJoinError(
                f"the hub at {endpoint} refused the TLS handshake: it accepts only certificates signed by "
                f"the graph's CA, and this process presented {own} (or the hub's certificate is not signed "
                f"by {tls.root_ca})"
            ) from None
        return
    close_session(probe)


def open_client(
    endpoint: str = DEFAULT_HUB,
    tls: TlsConfig | None = None,
    cancel: threading.Event | None = None,
    timeout_s: float | None = None,
    shared_memory: bool = True,
    retry: bool = True,
    shm_pool_mib: int | None = None,
    direct_links: bool = False,
) -> zenoh.Session | None:
    """A client session connected to the hub at `endpoint`, waiting for the hub as long as it takes.

    `direct_links=True`: a peer-mode session instead. It connects to the hub too, learns the other
    peers from it (gossip) and links to them directly over loopback, so what they send each other
    skips the hub: one process and one socket hop less per message (more messages per second, most
    of all for small messages: docs/experiments.md). For replicas on the hub's host only: it listens
    on 127.0.0.1.

    With `cancel` or `timeout_s`, the wait happens off the main thread so a signal can end it, or
    it gives up after `timeout_s`: returns None then. `shared_memory=False` for a session that
    outlives the processes it sweeps up after (the launcher): a segment it maps could never go.
    `retry=False`: no hub listening returns None at once. `shm_pool_mib` as in `zenoh_config`.
    Raises HubJoinError where this process cannot join a TLS hub (`check_tls_handshake`).
    """
    if tls is not None:
        check_tls_handshake(endpoint, tls)
    conf = zenoh_config(
        "peer" if direct_links else "client",
        listen=[DIRECT_LINK_LISTEN] if direct_links else None,
        connect=[endpoint],
        tls=tls,
        shared_memory=shared_memory,
        retry=retry,
        shm_pool_mib=shm_pool_mib,
    )
    if cancel is None and timeout_s is None:
        return zenoh.open(conf)
    cancel = cancel or threading.Event()
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    result: list[zenoh.Session] = []

    def connect() -> None:
        try:
            result.append(zenoh.open(conf))
        except zenoh.ZError as exc:  # nobody listens there (retry=False)
            log.debug("no hub at %s: %s", endpoint, exc)

    opener = threading.Thread(target=connect, daemon=True)
    opener.start()
    while opener.is_alive() and not cancel.is_set():
        opener.join(0.1)
        if deadline is not None and time.monotonic() > deadline:
            cancel.set()
    if result and cancel.is_set():
        close_session(result[0])
    return None if cancel.is_set() or not result else result[0]


def ask(session: zenoh.Session, key: str, command: dict, timeout_s: float) -> list[dict]:
    """Send `command` as a query to every queryable on `key` (each replica of an operator, or the
    launcher) and return their JSON answers. The query ends as soon as every receiver has answered,
    so `timeout_s` only matters for a receiver that hangs."""
    answers = []
    replies = session.get(
        key,
        payload=json.dumps(command),
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout_s,
        priority=CONTROL_PRIORITY,
        express=True,
    )
    for reply in replies:
        if reply.ok is not None:
            try:
                answers.append(json.loads(reply.ok.payload.to_bytes()))
            except ValueError:
                log.warning("unreadable answer on %s", reply.ok.key_expr)
    return answers


def answer(query: zenoh.Query, key: str, body: dict) -> None:
    """Answer a command query once and release it: the asker's query ends when all have answered."""
    query.reply(key, json.dumps(body))
    query.drop()


def live_replicas(session: zenoh.Session, keys: Keys, op: str = "*", timeout_s: float = 2.0) -> set[tuple[str, str]]:
    """(operator, replica) pairs holding a liveliness token right now."""
    found = set()
    for reply in session.liveliness().get(keys.live(op, "*"), timeout=timeout_s):
        if reply.ok is not None:
            found.add(keys.parse_live(str(reply.ok.key_expr)))
    return found


def close_session(session: zenoh.Session, timeout_s: float = 5.0) -> bool:
    """Close a session, giving up after `timeout_s`: with the hub gone, Zenoh's close can wait for a
    router that is not coming back, and a stopping operator must still exit."""
    done = threading.Thread(target=session.close, daemon=True)
    done.start()
    done.join(timeout_s)
    if done.is_alive():
        log.warning("session did not close within %.0fs (hub unreachable?); exiting anyway", timeout_s)
        return False
    return True


RECORDER = "_recorder"  # the launcher's recorder, in acks and liveliness: it acks every frame it recorded


class Keys:
    """Key names of one graph: `umad/<graph>/<operator>/<output>` and the underscore-prefixed service keys.

    A message whose effect depends on who sent it travels on a key that names the sender (acks,
    goodbyes, stats: `_ack/<op>/<replica>`), so the hub's access control can let each certificate
    write only under its own name, and the receiver checks that the key names the sender the message
    claims (`service_messages.py`)."""

    ALL_GRAPHS = "umad/*/_graph"  # every launcher on a hub answers here

    def __init__(self, graph: str):
        self.root = f"umad/{graph}"

    def data(self, op: str, output: str) -> str:
        return f"{self.root}/{op}/{output}"

    def pattern(self, source: str) -> str:
        """A graph source `op/output` (shell wildcards allowed, e.g. `diff_*/map`) as a key expression."""
        chunks = [c if c in ("*", "**") or "*" not in c else c.replace("*", "$*") for c in source.split("/")]
        return f"{self.root}/" + "/".join(chunks)

    def control(self, op: str) -> str:
        return f"{self.root}/_ctl/{op}"

    @property
    def control_all(self) -> str:
        return f"{self.root}/_ctl/**"

    @property
    def launcher(self) -> str:
        """Where `umad op start|stop` reach the launcher."""
        return self.control("_launcher")

    @property
    def graph_info(self) -> str:
        """The launcher answers here with the graph it runs: name, file, hub, operators."""
        return f"{self.root}/_graph"

    def resend(self, source: str) -> str:
        """Where an ordered operator asks source `source` to send a run's frames again (a rewind):
        a key of its own, apart from `_ctl`, so that the right to ask for frames is no right to command."""
        return f"{self.root}/_resend/{source}"

    def ack(self, op: str, replica: str) -> str:
        """Where replica `replica` of `op` (or the recorder) acks the frames it finished."""
        return f"{self.root}/_ack/{op}/{replica}"

    @property
    def ack_all(self) -> str:
        return f"{self.root}/_ack/*/*"

    def live(self, op: str, replica: str) -> str:
        return f"{self.root}/_live/{op}/{replica}"

    def left(self, op: str, replica: str) -> str:
        """Where replica `replica` of `op`, stopping on purpose, says goodbye before its token goes."""
        return f"{self.root}/_left/{op}/{replica}"

    @property
    def left_all(self) -> str:
        return f"{self.root}/_left/*/*"

    @property
    def live_all(self) -> str:
        return f"{self.root}/_live/**"

    def payload(self, op: str) -> str:
        """Under which prefix `op`'s replicas answer for payloads of their rings (`planes.ring.fetch_key`)."""
        return f"{self.root}/_payload/{op}"

    def stats(self, op: str, replica: str) -> str:
        return f"{self.root}/_stats/{op}/{replica}"

    def parse_data(self, key: str) -> tuple[str, str]:
        """`umad/<graph>/<op>/<output>` -> (op, output)."""
        rest = key[len(self.root) + 1 :]
        op, _, output = rest.partition("/")
        return op, output

    def parse_live(self, key: str) -> tuple[str, str]:
        """`umad/<graph>/_live/<op>/<replica>` -> (op, replica)."""
        parts = key.split("/")
        return parts[-2], parts[-1]

    def sender(self, key: str, service: str) -> tuple[str, str] | None:
        """The (operator, replica) that `key` names as its sender if it is `umad/<graph>/<service>/<op>/<replica>`
        (`service`: `_ack`, `_left` or `_stats`); None for any other key."""
        parts = key[len(self.root) + 1 :].split("/") if key.startswith(self.root + "/") else []
        return (parts[1], parts[2]) if len(parts) == 3 and parts[0] == service else None


class ShutdownSignal:
    """Turns SIGTERM/SIGINT into an event the main loop checks, so sessions are closed, not abandoned."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signum: int | None = None
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._handle)

    def _handle(self, signum, _frame) -> None:
        self.signum = signum
        self.event.set()

    @property
    def requested(self) -> bool:
        return self.event.is_set()


def _mapped_shm_files() -> set[str]:
    mapped: set[str] = set()
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            text = (proc / "maps").read_text()
        except OSError:
            continue
        for line in text.splitlines():
            if "/dev/shm/" in line:
                mapped.add(line.rsplit("/", 1)[-1].replace(" (deleted)", ""))
    return mapped


def cleanup_stale_shm() -> list[str]:
    """Unlink Zenoh shared-memory segments that no living process maps any more, and the payload
    rings of replicas that are gone (`remove_stale_rings`).

    Zenoh's own exit cleanup does not run in every case (a SIGKILLed replica, the receiver side's
    metadata segment), so the launcher sweeps after its children have exited. A segment still mapped
    by any process is never touched.
    """
    rings = remove_stale_rings()
    if not SHM_DIR.is_dir():
        return rings
    candidates = [p for p in SHM_DIR.glob("*.zenoh")]
    if not candidates:
        return rings
    mapped = _mapped_shm_files()
    removed = []
    for path in candidates:
        if path.name not in mapped:
            try:
                os.unlink(path)
                removed.append(path.name)
            except OSError:
                pass
    if removed:
        log.debug("removed %d stale shared-memory segments", len(removed))
    return rings + removed
