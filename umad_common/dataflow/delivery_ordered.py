"""The ordered path: lossless delivery to a stateful operator (the world model), which must see
each run's frames in seq order from seq 0. A complete frame waits until every earlier frame of its
run is finished; a run that starts past seq 0 here (this replica restarted mid-run) asks the
sources to send the run again from its first frame, so the operator's state, and every result
after it, equal those of a run without the restart.

Entry point: `OrderedDelivery.deliver(ready)`, called by the transform loop with the frames the
joiner has complete."""

from __future__ import annotations

import json
import time
from collections import defaultdict
from typing import TYPE_CHECKING

from umad_common.dataflow.messages import Message
from umad_common.dataflow.operator import Frame

if TYPE_CHECKING:
    from umad_common.dataflow.runtime import OperatorRuntime

REWIND_RETRY_S = 10.0


class OrderedDelivery:
    """Each run's frames finished in seq order, from its first frame."""

    def __init__(self, runtime: OperatorRuntime):
        self.rt = runtime
        self.next_seq: dict[str, int] = defaultdict(int)  # run -> the lowest seq still to process
        self.waiting: dict[str, dict[int, Frame]] = defaultdict(dict)  # run -> joined frames waiting their turn
        self.rewinds: dict[str, float] = {}  # run -> when its frames were last re-requested

    def accepts(self, msg: Message) -> bool:
        """Whether this replica joins `msg`: its frame's seq falls to this replica."""
        return self.rt.owns_seq(msg.seq)

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
        if self.next_seq[run] == 0 and 0 not in waiting:
            self._request_rewind(run, frame.seq)
        while self.next_seq[run] in waiting:
            self.rt.processor.finish(waiting.pop(self.next_seq[run]))
            self.next_seq[run] += 1

    def _request_rewind(self, run: str, seq: int) -> None:
        """An ordered operator that (re)started mid-run rebuilds its state by re-observing the run
        from its first frame: ask the sources to send frames [0, seq) again. Every other consumer
        sees those as duplicates and answers from its cache."""
        rt = self.rt
        now = time.monotonic()
        if now - self.rewinds.get(run, -1e9) < REWIND_RETRY_S:
            return
        self.rewinds[run] = now
        rt.log.warning("frame %s#%d arrived without the frames before it: asking the sources to resend them", run, seq)
        for source in rt.graph.sources():
            request = {"resend": {"run": run, "from": 0, "to": seq, "for": rt.op_id}}
            rt.session.put(rt.keys.control(source), json.dumps(request))

    def end_run(self, msg: Message) -> None:
        payloads = self.rt.processor.end_run(msg)
        if payloads is not None:
            self.next_seq.pop(msg.run, None)
            self.waiting.pop(msg.run, None)
            self.rt.processor.publish_and_ack(msg.run, msg.seq, payloads)
