"""Acks, goodbyes and resend requests: how each is written and read, and the check that its key
names the sender it claims.

An ack `{run, seq, op}` travels on `_ack/<op>/<replica>` and a goodbye `{op, replica}` on
`_left/<op>/<replica>` (msgpack). The hub lets each certificate write these only under its own
operator's name (`access.py`), and a reader takes one only where its key names the sender the
message claims, so a certificate acks and says goodbye as its own operator or not at all. A resend
request `{"resend": {run, from, to, for}}` (JSON) travels on `_resend/<source>`, which only the
source's ordered consumers may write, and the source takes nothing else there: the right to ask for
frames again is no right to command (`_ctl`). A message that fails these checks is ignored, counted
in `bad_messages` and logged once per key (`IgnoredMessages`).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass

import msgpack

from umad_common.dataflow.delivery.stats import Stats
from umad_common.dataflow.transport.bus import Keys

RESEND_FIELDS = {"run": str, "from": int, "to": int, "for": str}


class ServiceMessageError(ValueError):
    """An ack, goodbye or resend request that is malformed, or whose key names another sender."""


@dataclass(frozen=True)
class Ack:
    run: str
    seq: int
    op: str  # the operator (or the recorder) that finished the frame


def encode_ack(run: str, seq: int, op: str) -> bytes:
    return msgpack.packb({"run": run, "seq": seq, "op": op})


def read_ack(keys: Keys, key: str, raw: bytes) -> Ack:
    """The ack on `key`; ServiceMessageError when it is malformed or claims another sender than its key."""
    body = _unpacked(raw, "an ack {run, seq, op}")
    try:
        ack = Ack(str(body["run"]), int(body["seq"]), str(body["op"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ServiceMessageError(f"not an ack {{run, seq, op}}: {exc!r}") from None
    _check_sender(keys.sender(key, "_ack"), ack.op, None)
    return ack


def encode_goodbye(op: str, replica: str) -> bytes:
    return msgpack.packb({"op": op, "replica": replica})


def read_goodbye(keys: Keys, key: str, raw: bytes) -> tuple[str, str]:
    """The (operator, replica) saying goodbye on `key`; ServiceMessageError when the message is
    malformed or names another replica than its key."""
    body = _unpacked(raw, "a goodbye {op, replica}")
    try:
        op, replica = str(body["op"]), str(body["replica"])
    except (KeyError, TypeError) as exc:
        raise ServiceMessageError(f"not a goodbye {{op, replica}}: {exc!r}") from None
    _check_sender(keys.sender(key, "_left"), op, replica)
    return op, replica


def encode_resend(run: str, first: int, last: int, requester: str) -> bytes:
    """Ask for frames [first, last) of `run` again, for operator `requester`."""
    return json.dumps({"resend": {"run": run, "from": first, "to": last, "for": requester}}).encode()


def read_resend(raw: bytes) -> dict:
    """The request `{run, from, to, for}` of a resend message: exactly one key, `resend`, and those
    four fields, or ServiceMessageError (a `stop`, a `set`, anything else)."""
    try:
        body = json.loads(raw)
    except ValueError:
        body = None
    request = body.get("resend") if isinstance(body, dict) and set(body) == {"resend"} else None
    if not (
        isinstance(request, dict)
        and set(request) == set(RESEND_FIELDS)
        and all(type(request[name]) is kind for name, kind in RESEND_FIELDS.items())
        and 0 <= request["from"] <= request["to"]
    ):
        raise ServiceMessageError(
            f"not a resend request {{'resend': {{run, from, to, for}}}}, the only message taken here: {bytes(raw[:120])!r}"
        )
    return request


def _unpacked(raw: bytes, what: str) -> dict:
    try:
        body = msgpack.unpackb(raw)
    except Exception as exc:  # msgpack raises several kinds on garbage
        raise ServiceMessageError(f"not {what}: {type(exc).__name__}") from None
    if not isinstance(body, dict):
        raise ServiceMessageError(f"not {what}: a {type(body).__name__}")
    return body


def _check_sender(sender: tuple[str, str] | None, op: str, replica: str | None) -> None:
    """ServiceMessageError unless the key's `sender` (operator, replica) is `op` (and `replica`, if given)."""
    if sender is None or sender[0] != op or (replica is not None and sender[1] != replica):
        claimed = op if replica is None else f"{op}.{replica}"
        raise ServiceMessageError(f"claims to come from {claimed}, but its key names {sender or 'no sender'}")


class IgnoredMessages:
    """What a replica ignores on the keys it listens to (a forged ack, a command on the resend key):
    counted in `bad_messages`, logged the first time per key, so a flood adds no log lines."""

    def __init__(self, log: logging.Logger, stats: Stats):
        self.log = log
        self.stats = stats
        self.logged: set[str] = set()

    def ignore(self, key: str, exc: ServiceMessageError) -> None:
        self.stats.bad_messages += 1
        if key not in self.logged:
            self.logged.add(key)
            self.log.warning("ignored a message on %s: %s (later ones there are only counted)", key, exc)
