"""The ordered path: lossless delivery to a stateful operator (the world model), which must see
each run's frames in seq order from seq 0. A complete frame waits until every earlier frame of its
run is finished; a run that starts past seq 0 here (this replica restarted mid-run, or took the run
over from a replica that died) asks the sources to send the run again from its first frame, so the
operator's state, and every result after it, equal those of a run without the restart.

Keyed replicas (`replicas: k` on an ordered operator, the keyed streams of Flink or Kafka
Streams): each run belongs to one replica (`RunOwners`), which sees all of its frames; the others
pass them by. Liveliness tokens alone say who is alive.

Entry point: `OrderedDelivery.deliver(ready)`, called by the transform loop with the frames the
joiner has complete."""

from __future__ import annotations

import hashlib
import time
from collections import defaultdict

from umad_common.dataflow.api.messages import Message
from umad_common.dataflow.api.operator import Frame
from umad_common.dataflow.delivery.paths import DeliveryHost, FrameFinisher

REWIND_RETRY_S = 10.0


def rendezvous_score(run: str, replica: str) -> int:
    """The replica's score for the run (rendezvous or highest-random-weight hashing): the same on
    every host and in every process, unlike Python's `hash`."""
    digest = hashlib.blake2b(f"{run}/{replica}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


class RunOwners:
    """Which replica of an ordered operator owns each run, as every replica works it out alone from
    the same facts: the run's frames and the replicas' liveliness tokens.

    A run's candidates are the replicas alive when it starts (its frame 0 seen); its owner is the
    candidate, still alive, with the highest `rendezvous_score`. A replica that joins later is no
    candidate for a run already under way, so a run never moves to a newcomer; a replica whose
    token goes is out of every run for good, and the candidate with the next score takes its runs
    (the others keep theirs). A replica that first sees a run mid-way, or before its own token came
    back from the hub (the others may not know it yet), counts only the others; where it is alone,
    the run is its own. Should two replicas ever disagree all the same (one saw a token the other
    had not yet), both compute the run: the results are the same bytes and every consumer keeps the
    first, only the work is done twice.
    """

    def __init__(self, me: str):
        self.me = me
        self.candidates: dict[str, set[str]] = {}  # run -> replicas that may own it

    def owner(self, run: str, seq: int, alive: set[str]) -> str:
        """The run's owner; `seq` is the frame at hand, `alive` the replicas whose token this
        replica sees now (itself once its own token came back)."""
        candidates = self.candidates.get(run)
        if candidates is None:
            candidates = set(alive) if seq == 0 and self.me in alive else alive - {self.me}
            self.candidates[run] = candidates = candidates or {self.me}
        living = candidates & (alive | {self.me})
        if not living:  # every replica alive at the run's start is gone: the survivors share it
            living = self.candidates[run] = alive | {self.me}
        return max(living, key=lambda replica: rendezvous_score(run, replica))

    def replica_gone(self, replica: str, alive: set[str]) -> list[str]:
        """A replica's token went: it is out of every run. Returns the runs this replica owns now
        and did not before."""
        taken = []
        for run, candidates in self.candidates.items():
            if replica not in candidates:
                continue
            before = self.owner(run, 1, alive | {replica})
            candidates.discard(replica)
            if before != self.me and self.owner(run, 1, alive) == self.me:
                taken.append(run)
        return taken


class OrderedDelivery:
    """Each run's frames finished in seq order, from its first frame."""

    def __init__(self, host: DeliveryHost, finisher: FrameFinisher):
        self.host = host
        self.finisher = finisher
        self.next_seq: dict[str, int] = defaultdict(int)  # run -> the lowest seq still to process
        self.waiting: dict[str, dict[int, Frame]] = defaultdict(dict)  # run -> joined frames waiting their turn
        self.rewinds: dict[str, float] = {}  # run -> when its frames were last re-requested
        self.newest_seen: dict[str, int] = {}  # run -> the newest seq that arrived, owned or not

    def accepts(self, msg: Message) -> bool:
        """Whether this replica joins `msg`: its run belongs to this replica."""
        self.newest_seen[msg.run] = max(msg.seq, self.newest_seen.get(msg.run, 0))
        return self.host.owns_run(msg.run, msg.seq)

    def take_over(self, runs: list[str]) -> None:
        """Runs whose owner died are this replica's now: ask the sources for each from its first
        frame up to the newest that arrived here, rather than wait for their re-send timeout."""
        for run in runs:
            if run in self.finisher.ended or run not in self.newest_seen:
                continue
            if self._request_rewind(run, self.newest_seen[run] + 1):
                self.host.log.warning("run %s: its replica is gone; taking it over from its first frame", run)

    def deliver(self, ready: list[Frame]) -> None:
        for frame in ready:
            self._finish_in_order(frame)

    def _finish_in_order(self, frame: Frame) -> None:
        """Hold a frame until every earlier frame of its run is finished; a run that starts past
        seq 0 (this replica restarted) asks the sources for the frames before it."""
        run = frame.run
        if frame.seq < self.next_seq[run]:
            return
        waiting = self.waiting[run]
        waiting[frame.seq] = frame
        if self.next_seq[run] == 0 and 0 not in waiting and self._request_rewind(run, frame.seq):
            self.host.log.warning(
                "frame %s#%d arrived without the frames before it: asking the sources to resend them", run, frame.seq
            )
        while self.next_seq[run] in waiting:
            self.finisher.finish(waiting.pop(self.next_seq[run]))
            self.next_seq[run] += 1

    def _request_rewind(self, run: str, seq: int) -> bool:
        """An ordered operator that (re)started mid-run rebuilds its state by re-observing the run
        from its first frame: ask the sources to send frames [0, seq) again. Every other consumer
        sees those as duplicates and answers from its cache. False when the run was asked for less
        than REWIND_RETRY_S ago (nothing sent)."""
        now = time.monotonic()
        if now - self.rewinds.get(run, -1e9) < REWIND_RETRY_S:
            return False
        self.rewinds[run] = now
        self.host.request_resend(run, 0, seq)
        return True

    def end_run(self, msg: Message) -> None:
        payloads = self.finisher.end_run(msg)
        if payloads is not None:
            self.next_seq.pop(msg.run, None)
            self.waiting.pop(msg.run, None)
            self.finisher.publish_and_ack(msg.run, msg.seq, payloads)
