"""The delivery settings, declared once: how a source paces its frames, and how long a joining
operator waits for a late input in live mode. The runtime reads them from these fields and nowhere
else; an operator's own `Params` extends the class that applies to it, so `umad set` and `--set`
reach them like any other parameter (`replayer.window=4`, `fusion.deadline_ms=200`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class SourceParams(BaseModel):
    """Every source's parameters start with these (`Source.Params` extends this class)."""

    model_config = ConfigDict(extra="forbid")

    pacing: Literal["lossless", "realtime"] = Field(
        "lossless", description="lossless: advance on acks from the sinks; realtime: publish at rate_hz"
    )
    window: int = Field(8, ge=1, description="lossless pacing: frames in flight before waiting for acks")
    rate_hz: float = Field(10.0, gt=0, description="realtime pacing: frames published per second")
    ack_timeout_s: float = Field(15.0, gt=0, description="lossless pacing: re-send a frame not acked within this time")
    runs_in_flight: int = Field(
        1,
        ge=1,
        description="lossless pacing: runs sent side by side, their frames taken in turn, each with its own window: "
        "replicas of an ordered operator (the world model) then work on different runs at once. Needs a source "
        "that reads its frames in any order (`Source.runs`)",
    )

    @model_validator(mode="after")
    def _side_by_side_is_lossless(self) -> SourceParams:
        if self.runs_in_flight > 1 and self.pacing != "lossless":
            raise ValueError(
                f"runs_in_flight {self.runs_in_flight} needs pacing lossless; a realtime source sends one run"
            )
        return self


class JoinParams(BaseModel):
    """Parameters of an operator with a wildcard input that may fuse without a late producer."""

    model_config = ConfigDict(extra="forbid")

    deadline_ms: float = Field(
        default=500.0,
        gt=0,
        description="live mode: how long after a frame's first input to wait for the other expected producers "
        "before using those that arrived (the output is then marked partial); lossless mode always waits",
    )
