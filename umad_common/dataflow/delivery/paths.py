"""What the three delivery paths (`replay.py`, `ordered.py`, `live.py`) share: the interface the
replica's transform loop calls (`DeliveryPath`), and what the paths themselves use of the replica
that runs them (`DeliveryHost`) and of the frame processor that finishes their frames
(`FrameFinisher`). The paths see the process that runs them only through these, so this layer
never imports the one above it; `OperatorRuntime` and `FrameProcessor` fit them as they are."""

from __future__ import annotations

import logging
from typing import Protocol

from umad_common.dataflow.api.messages import Message
from umad_common.dataflow.api.operator import Frame


class DeliveryPath(Protocol):
    """One way of delivering the frames a replica joined: replay, ordered or live."""

    def accepts(self, msg: Message) -> bool:
        """Whether this replica joins `msg` (its frame falls to this replica and is still wanted)."""
        ...

    def deliver(self, ready: list[Frame]) -> None:
        """Finish, hold or pass over the frames the joiner has complete (possibly none)."""
        ...

    def end_run(self, msg: Message) -> None:
        """A run's end-of-run marker."""
        ...


class DeliveryHost(Protocol):
    """What a delivery path uses of the replica that runs it: which frames fall to it, how long a
    partly joined frame may wait, a rewind request to the sources, and its logger."""

    log: logging.Logger

    def owns_seq(self, seq: int) -> bool:
        """Whether frame `seq` falls to this replica (frames split by seq over the live replicas)."""
        ...

    def owns_run(self, run: str, seq: int) -> bool:
        """Ordered operators: whether `run` belongs to this replica (`RunOwners`); `seq` is the frame at hand."""
        ...

    def deadline_s(self) -> float:
        """How long a partly joined frame may wait in live mode (read each time: a parameter)."""
        ...

    def request_resend(self, run: str, first: int, end: int) -> None:
        """Ask every source upstream of this operator to send frames [first, end) of `run` again."""
        ...


class FrameFinisher(Protocol):
    """What a delivery path uses of the frame processor (`FrameProcessor`), the one place that
    computes, caches, publishes and acks the frames a path decided to finish or pass over."""

    ended: dict[str, list[tuple[str, bytes]]]  # run -> its end-of-run payloads, once the run is closed
    compute_s: float  # running mean of the wall time the operator's `process` takes (live mode's catch-up)

    def marker_meta(self, frame: Frame) -> dict | None:
        """The meta of the marker `frame` is passed on as without computing; None for a frame to compute."""
        ...

    def finish(self, frame: Frame) -> None:
        """Process one joined frame (or pass on its marker), cache and publish the result."""
        ...

    def pass_over(self, run: str, seq: int, stamp_ns: int) -> None:
        """Live mode: send a superseded marker for a frame this operator will not process."""
        ...

    def end_run(self, msg: Message) -> list[tuple[str, bytes]] | None:
        """Call the operator's `end_run` once; the marker's payloads, or None for a re-sent marker."""
        ...

    def publish_and_ack(self, run: str, seq: int, payloads: list[tuple[str, bytes]]) -> None:
        """Publish a frame's (or an end-of-run marker's) payloads; a sink then acks it end to end."""
        ...
