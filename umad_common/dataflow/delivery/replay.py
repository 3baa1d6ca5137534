"""The replay path: lossless delivery (a source that re-sends what was not acked) to an operator
that keeps no state between frames. Each joined frame is finished as soon as it is complete, in
whatever order frames complete; replicas split a run's frames by seq over the live replica set
(`DeliveryHost.owns_seq`), so k replicas share every run.

Entry point: `ReplayDelivery.deliver(ready)`, called by the transform loop with the frames the
joiner has complete."""

from __future__ import annotations

from umad_common.dataflow.api.messages import Message
from umad_common.dataflow.api.operator import Frame
from umad_common.dataflow.delivery.paths import DeliveryHost, FrameFinisher


class ReplayDelivery:
    """Every complete frame finished at once, in any order."""

    def __init__(self, host: DeliveryHost, finisher: FrameFinisher):
        self.host = host
        self.finisher = finisher

    def accepts(self, msg: Message) -> bool:
        """Whether this replica joins `msg`: its frame's seq falls to this replica."""
        return self.host.owns_seq(msg.seq)

    def deliver(self, ready: list[Frame]) -> None:
        for frame in ready:
            self.finisher.finish(frame)

    def end_run(self, msg: Message) -> None:
        payloads = self.finisher.end_run(msg)
        if payloads is not None:
            self.finisher.publish_and_ack(msg.run, msg.seq, payloads)
