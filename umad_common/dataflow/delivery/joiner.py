"""The bookkeeping of the delivery protocol: joining inputs by `(run, seq)`, who is live and what
was already computed. Plain data structures, no Zenoh, so the runtime reads as the protocol itself."""

from __future__ import annotations

import time
from collections import OrderedDict, defaultdict
from dataclasses import dataclass, field

from umad_common.dataflow.api.messages import Message
from umad_common.dataflow.api.operator import Frame

OUTPUT_CACHE_FRAMES = 64
MAX_PENDING_FRAMES = 256
REPUBLISH_INTERVAL_S = 1.0
LOST_GRACE_S = 15.0


@dataclass
class _Pending:
    first_seen: float
    stamp_ns: int
    single: dict[str, Message] = field(default_factory=dict)
    many: dict[str, dict[str, Message]] = field(default_factory=lambda: defaultdict(dict))


class FrameJoiner:
    """Collects the inputs of each `(run, seq)` and hands out complete frames.

    A frame is complete when every single port has its message and every `many` port has a message
    from each producer expected right now (the live operators matching its wildcard). With a
    deadline, a frame that waited longer is handed out as partial. At most `max_pending` frames
    wait; beyond that the oldest is dropped and counted (the source's retransmission recovers it).
    """

    def __init__(self, single_ports: list[str], many_ports: list[str], max_pending: int = MAX_PENDING_FRAMES):
        self.single_ports = single_ports
        self.many_ports = many_ports
        self.max_pending = max_pending
        self.pending: OrderedDict[tuple[str, int], _Pending] = OrderedDict()
        self.dropped = 0
        self.joined = 0
        self.wait_s = 0.0  # summed over joined frames: first input to complete

    def add(self, port: str, producer: str, msg: Message) -> None:
        key = (msg.run, msg.seq)
        entry = self.pending.get(key)
        if entry is None:
            entry = self.pending[key] = _Pending(time.monotonic(), msg.stamp_ns)
            if len(self.pending) > self.max_pending:
                self.pending.popitem(last=False)
                self.dropped += 1
        if port in self.many_ports:
            entry.many[port][producer] = msg
        else:
            entry.single[port] = msg

    def discard(self, key: tuple[str, int]) -> None:
        self.pending.pop(key, None)

    def discard_older(self, run: str, seq: int) -> dict[int, int]:
        """Forget the frames of `run` before `seq` still waiting for inputs; returns their
        {seq: stamp_ns}."""
        older = {key[1]: entry.stamp_ns for key, entry in self.pending.items() if key[0] == run and key[1] < seq}
        for s in older:
            del self.pending[(run, s)]
        return older

    def pop_expired(self, deadline_s: float, finished: dict[str, int]) -> dict[tuple[str, int], int]:
        """Forget the frames still not ready after `deadline_s` that are older than a frame of their
        run already finished (`finished`: run -> newest finished seq + 1): live mode, their input
        was lost. Returns their {(run, seq): stamp_ns}."""
        now = time.monotonic()
        expired = {
            key: entry.stamp_ns
            for key, entry in self.pending.items()
            if now - entry.first_seen > deadline_s and key[1] < finished.get(key[0], 0)
        }
        for key in expired:
            del self.pending[key]
        return expired

    def pop_ready(self, expected: dict[str, set[str]], deadline_s: float = 0.0) -> list[Frame]:
        now = time.monotonic()
        ready = []
        for key, entry in list(self.pending.items()):
            if len(entry.single) < len(self.single_ports):
                continue
            complete = all(entry.many[p] and expected.get(p, set()) <= set(entry.many[p]) for p in self.many_ports)
            late = (
                deadline_s > 0 and now - entry.first_seen > deadline_s and all(entry.many[p] for p in self.many_ports)
            )
            if complete or late:
                del self.pending[key]
                self.joined += 1
                self.wait_s += now - entry.first_seen
                ready.append(
                    Frame(
                        run=key[0],
                        seq=key[1],
                        stamp_ns=entry.stamp_ns,
                        inputs=dict(entry.single),
                        many={p: dict(entry.many[p]) for p in self.many_ports},
                        partial=not complete,
                    )
                )
        return ready


class Membership:
    """Which replicas of which operators are in the graph now, from liveliness tokens.

    A token that vanishes without a goodbye (a crash, or the hub restarting under everyone) is kept
    for `grace_s`: waiting a little for a restarted replica beats completing frames without its
    output. A replica that stops on purpose says so on the `_left` key first and drops out at once.
    """

    def __init__(self, grace_s: float = LOST_GRACE_S):
        self.grace_s = grace_s
        self.live: dict[str, set[str]] = defaultdict(set)
        self.lost: dict[tuple[str, str], float] = {}
        self.left: set[tuple[str, str]] = set()

    def put(self, op: str, rep: str) -> None:
        self.live[op].add(rep)
        self.lost.pop((op, rep), None)
        self.left.discard((op, rep))

    def delete(self, op: str, rep: str) -> None:
        self.live[op].discard(rep)
        if (op, rep) in self.left:
            self.left.discard((op, rep))
        else:
            self.lost[(op, rep)] = time.monotonic()

    def leave(self, op: str, rep: str) -> None:
        if self.lost.pop((op, rep), None) is None:
            self.left.add((op, rep))

    def expire(self) -> bool:
        """Forget replicas lost longer than the grace period; True if any was forgotten."""
        now = time.monotonic()
        gone = [k for k, t in self.lost.items() if now - t > self.grace_s]
        for k in gone:
            del self.lost[k]
        return bool(gone)

    def replicas(self, op: str) -> set[str]:
        return self.live.get(op, set()) | {rep for (o, rep) in self.lost if o == op}

    def ops(self) -> set[str]:
        return {op for op, reps in self.live.items() if reps} | {op for op, _ in self.lost}


class OutputCache:
    """Recent outputs by `(run, seq)`: a duplicate input re-publishes these bytes, never recomputes."""

    def __init__(self, size: int = OUTPUT_CACHE_FRAMES):
        self.size = size
        self.entries: OrderedDict[tuple[str, int], list[tuple[str, bytes]]] = OrderedDict()
        self.last_republish: dict[tuple[str, int], float] = {}

    def __contains__(self, key: tuple[str, int]) -> bool:
        return key in self.entries

    def put(self, key: tuple[str, int], payloads: list[tuple[str, bytes]]) -> None:
        self.entries[key] = payloads
        while len(self.entries) > self.size:
            old, _ = self.entries.popitem(last=False)
            self.last_republish.pop(old, None)

    def due_for_republish(self, key: tuple[str, int]) -> list[tuple[str, bytes]]:
        """The cached payloads, at most once per REPUBLISH_INTERVAL_S per frame (one duplicate per port arrives)."""
        now = time.monotonic()
        if now - self.last_republish.get(key, 0.0) < REPUBLISH_INTERVAL_S:
            return []
        self.last_republish[key] = now
        return self.entries[key]
