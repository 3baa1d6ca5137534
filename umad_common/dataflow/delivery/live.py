"""The live path: a source that paces in real time and never re-sends (a camera). Waiting gives
way to keeping up: an operator computes the newest frames it has ready, as many as it can in one
camera period, and passes the older ones over (meta `superseded`, counted in `superseded`); a frame
still waiting for an input after its deadline is passed over too. So a lost payload never holds an
operator, a slow operator never works through a backlog, and a cheap one catches up after a stall.

Entry point: `LiveDelivery.deliver(ready)`, called by the transform loop with the frames the joiner
has complete (possibly none: it also passes over the frames whose deadline went by)."""

from __future__ import annotations

from collections import defaultdict

from umad_common.dataflow.api.messages import Message
from umad_common.dataflow.api.operator import Frame
from umad_common.dataflow.delivery.joiner import FrameJoiner
from umad_common.dataflow.delivery.paths import DeliveryHost, FrameFinisher

CATCH_UP_PERIODS = 2  # an operator computes the newest ready frames it can in this many camera periods


class LiveDelivery:
    """The newest ready frames of each run that fit in the camera's time; the older ones passed over."""

    def __init__(
        self, host: DeliveryHost, *, finisher: FrameFinisher, joiner: FrameJoiner, ordered: bool, frame_period_s: float
    ):
        """`ordered`: a stateful operator, whose frames fall to it by run and which cannot go back;
        `frame_period_s`: the time between two frames of the fastest realtime source."""
        self.host = host
        self.finisher = finisher
        self.joiner = joiner
        self.ordered = ordered
        self.frame_period_s = frame_period_s
        self.next_seq: dict[str, int] = defaultdict(int)  # run -> the seq after the newest frame finished

    def accepts(self, msg: Message) -> bool:
        """Whether this replica joins `msg`: its frame falls to this replica (its run, for an ordered
        operator; its seq otherwise), and it was not already finished or passed over (a late input)."""
        host = self.host
        if not (host.owns_run(msg.run, msg.seq) if self.ordered else host.owns_seq(msg.seq)):
            return False
        return not (msg.seq < self.next_seq[msg.run] and (msg.run, msg.seq) not in self.joiner.pending)

    def deliver(self, ready: list[Frame]) -> None:
        """Finish what is ready (`_finish_live`), then pass over the frames whose input never came."""
        self._finish_live(ready)
        for (run, seq), stamp_ns in self.joiner.pop_expired(self.host.deadline_s(), self.next_seq).items():
            self.finisher.pass_over(run, seq, stamp_ns)

    def _finish_live(self, ready: list[Frame]) -> None:
        """A camera's consumer wants every frame it can have, soon, and never a backlog; a frame
        lost on the way never comes again (live sources do not re-send).

        The rule, per run: of the ready frames to compute, the newest ones this operator can compute
        in `CATCH_UP_PERIODS` camera periods (by its running mean compute time; at least the newest)
        are processed, oldest first, and the older ones are passed over. One period is a frame's
        own; the second absorbs one stall of a busy machine, while a longer stall is passed over
        rather than queued. A passed-over frame is counted in `superseded` and sent on as a
        marker with meta `superseded`, so the sinks ack it and the operators after this one pass it
        on without computing. Frames that need no computing (an input is an error, skip or
        superseded marker) are passed on at once and do not compete.

        A frame still waiting for an input while a newer one was processed stays until its deadline
        (`DeliveryHost.deadline_s`; then it is passed over, `FrameJoiner.pop_expired`), and is
        processed if it completes before: a join whose inputs came by paths of different speed loses
        nothing. The newest frame is never given up (a slow input is no lost one); at the run's end
        the frames still waiting are passed over (`end_run`). An ordered operator, which
        cannot go back, passes over its older waiting frames when it processes a newer one; it thus
        sees its run's frames in increasing seq order with gaps (the world model bridges a gap),
        and a replica restarted mid-run starts from the newest frame (no rewind: a live source's old
        frames are worthless).
        """
        finisher = self.finisher
        to_compute: list[Frame] = []
        for frame in sorted(ready, key=lambda f: f.seq):
            if finisher.marker_meta(frame) is None:
                to_compute.append(frame)
            else:
                finisher.finish(frame)
        budget_s = CATCH_UP_PERIODS * self.frame_period_s
        fits = max(1, int(budget_s / finisher.compute_s)) if finisher.compute_s > 0 else len(to_compute)
        for run in dict.fromkeys(frame.run for frame in to_compute):
            frames = [frame for frame in to_compute if frame.run == run]
            for frame in frames[:-fits]:
                finisher.pass_over(run, frame.seq, frame.stamp_ns)
            for frame in frames[-fits:]:
                if self.ordered:
                    for seq, stamp_ns in sorted(self.joiner.discard_older(run, frame.seq).items()):
                        finisher.pass_over(run, seq, stamp_ns)
                self.next_seq[run] = max(self.next_seq[run], frame.seq + 1)
                finisher.finish(frame)

    def end_run(self, msg: Message) -> None:
        """Close the run; its frames still waiting for an input the source gave up on are passed over."""
        payloads = self.finisher.end_run(msg)
        if payloads is None:
            return
        for seq, stamp_ns in sorted(self.joiner.discard_older(msg.run, msg.seq).items()):
            self.finisher.pass_over(msg.run, seq, stamp_ns)
        self.next_seq.pop(msg.run, None)
        self.finisher.publish_and_ack(msg.run, msg.seq, payloads)
