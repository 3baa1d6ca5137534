"""What an operator module writes: its ports, its parameter schema and one per-frame function.

Everything else (connecting to the hub, joining inputs by `(run, seq)`, ordering, acks, dedup,
stats, shutdown) lives in `umad_common.dataflow.process.runtime`. An operator is plain Python: construct it with its
parameters and call `process(frame)` in a unit test, no Zenoh needed.

    class Negate(Operator):
        kind = "negate"
        inputs = (Input("x"),)
        outputs = ("y",)

        class Params(BaseModel):
            scale: float = 1.0

        def process(self, frame):
            x = frame.inputs["x"].arrays["value"]
            return {"y": Output({"value": -self.params.scale * x})}
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from umad_common import resolve_path
from umad_common.dataflow.api.messages import Message
from umad_common.dataflow.api.pacing import SourceParams
from umad_common.dataflow.api.plugins import import_class


class NoParams(BaseModel):
    """Parameter schema of an operator that takes none."""

    model_config = ConfigDict(extra="forbid")


@dataclass(frozen=True)
class Input:
    """An input port. `many=True` ports take a wildcard source (e.g. `diff_*/map`) and receive a
    dict `{producer_id: Message}` of every live producer that matched. An `optional` port may stay
    unwired; frames then join without it (`Operator.wiring_problems` says when it is needed)."""

    name: str
    many: bool = False
    optional: bool = False


@dataclass
class Output:
    """What `process` returns per output port; the runtime adds run, seq, stamp and producer."""

    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class Frame:
    """The joined inputs of one `(run, seq)`."""

    run: str
    seq: int
    stamp_ns: int
    inputs: dict[str, Message] = field(default_factory=dict)
    many: dict[str, dict[str, Message]] = field(default_factory=dict)
    partial: bool = False  # a `many` port was emitted at its deadline without every expected producer

    @property
    def frame_id(self) -> str:
        return f"{self.run}#{self.seq}"


def delivered(
    outputs: Mapping[str, Output], run: str, seq: int, stamp_ns: int = 0, producer: str = ""
) -> dict[str, Message]:
    """One frame's outputs as the messages its consumers receive, by output port (the runtime also
    records the producer's parameters in each meta; in-process callers go without)."""
    return {port: Message(run, seq, stamp_ns, producer, out.meta, out.arrays) for port, out in outputs.items()}


def frame_of(
    outputs: Mapping[str, Output], ports: Iterable[str], run: str, seq: int, stamp_ns: int = 0, producer: str = ""
) -> Frame:
    """The frame an operator is handed when each of its input `ports` is wired to the output of the
    same name: how a recorded or generated frame (`frame_outputs` of the replayer, a bench's
    drive) becomes an operator's inputs outside a running graph."""
    return Frame(run, seq, stamp_ns, inputs=delivered({p: outputs[p] for p in ports}, run, seq, stamp_ns, producer))


class MissingInputError(ValueError):
    """A frame's input lacks an array the operator reads."""


def input_array(frame: Frame, port: str, name: str, operator: str, producer: str | None = None) -> np.ndarray:
    """Array `name` of input `port` (of `producer`'s message on a `many` port). Raises
    `MissingInputError` naming the operator, the frame, the port, the array and what arrived."""
    message = frame.inputs.get(port) if producer is None else frame.many.get(port, {}).get(producer)
    if message is None or name not in message.arrays:
        where = f"input {port!r}" if producer is None else f"input {port!r} from {producer!r}"
        arrived = "no message" if message is None else f"arrays {sorted(message.arrays)}"
        raise MissingInputError(f"{operator} {frame.frame_id}: {where} lacks array {name!r}; got {arrived}")
    return message.arrays[name]


@dataclass
class Context:
    """Where an operator runs: its id in the graph, its replica index, where relative paths resolve."""

    op_id: str = "local"
    replica: int = 0
    graph_name: str = "umad"
    base_dir: Path = field(default_factory=Path.cwd)
    log: logging.Logger = field(default_factory=lambda: logging.getLogger("umad.op"))

    def resolve(self, path: str | Path) -> Path:
        """A path from the parameters: absolute, or relative to the graph's `base_dir`; failing
        that, the shipped file it names, so the `umad_common/assets/...` defaults work for a graph
        kept in any folder (`umad_common.resolve_path`)."""
        return resolve_path(path, self.base_dir)


class Operator:
    """Base class of every operator kind.

    Class attributes:
        kind: the name graph.yaml uses.
        inputs / outputs: the ports.
        Params: a pydantic model; unknown keys are refused (set `extra="forbid"`).
        ordered: frames of a run arrive in seq order, starting at 0 (stateful operators); with
            `replicas: k` each run goes to one replica, which keeps the run's state. In live mode (a realtime source) the seqs still
            increase but may skip: a frame lost on the way, or stale once a newer one was ready, is
            passed over, and the operator handles the gap it sees in seq (the world model bridges it).
        end_of_run_outputs: `end_run` may return outputs (e.g. the accumulator's final metrics).
        fixed_params: parameters read once when the operator is built (its weights, its device):
            `umad set` refuses to change them; the operator is restarted for a new value.
    """

    kind: ClassVar[str] = ""
    inputs: ClassVar[tuple[Input, ...]] = ()
    outputs: ClassVar[tuple[str, ...]] = ()
    Params: ClassVar[type[BaseModel]] = NoParams
    ordered: ClassVar[bool] = False
    fixed_params: ClassVar[tuple[str, ...]] = ()

    def __init__(self, params: BaseModel | dict | None = None, context: Context | None = None):
        self.context = context or Context()
        self.params = self.validate_params(params or {})

    @classmethod
    def validate_params(cls, params: BaseModel | dict) -> BaseModel:
        """Check parameters against the schema (raises pydantic.ValidationError naming the field)."""
        if isinstance(params, cls.Params):
            return params
        return cls.Params.model_validate(dict(params))

    @classmethod
    def input_paths(cls, params: BaseModel) -> dict[str, str]:
        """The files or folders these (valid) parameters name that the operator reads at start,
        `{parameter: path as written}`: a launcher checks they exist before it starts anything."""
        return {}

    @classmethod
    def wiring_problems(cls, params: BaseModel, wired: set[str]) -> list[str]:
        """What `umad graph check` should refuse about these (valid) parameters given the wired input
        ports, e.g. an optional port the chosen method reads; empty when all is well."""
        return []

    def update_params(self, params: BaseModel) -> None:
        """Called between frames when the control key changes a parameter (already validated); a
        change of one of `fixed_params` is refused."""
        for name in self.fixed_params:
            if getattr(params, name) != getattr(self.params, name):
                raise ValueError(
                    f"{self.kind}: `{name}` cannot change at runtime; restart the operator with the new value"
                )
        self.params = params

    def process(self, frame: Frame) -> dict[str, Output]:
        """Compute this frame's outputs. Raising skips the frame (logged with its id and counted)."""
        raise NotImplementedError

    def end_run(self, run: str) -> dict[str, Output]:
        """Called once when a run has ended and all its frames were processed."""
        return {}

    def close(self) -> None:
        """Release resources at shutdown."""


@dataclass
class SourceFrame:
    """One frame a source emits."""

    run: str
    seq: int
    stamp_ns: int
    outputs: dict[str, Output] = field(default_factory=dict)
    raw: dict[str, bytes] = field(default_factory=dict)  # port -> payload published verbatim (log replay)
    error: str | None = None  # the frame could not be read: it travels on as an error marker


class Source(Operator):
    """An operator with no inputs that produces frames (the replayer). The runtime paces it:
    at most `window` frames in flight, advancing on acks from the graph's sinks. Its `Params`
    extend `SourceParams`, which hold the pacing settings."""

    Params: ClassVar[type[BaseModel]] = SourceParams

    def frames(self) -> Iterator[SourceFrame]:
        """Yield frames run after run, seq 0, 1, 2, ... within a run."""
        raise NotImplementedError

    def frame_at(self, run: str, seq: int) -> SourceFrame:
        """One earlier frame again, identical to what `frames` yielded: lets a restarted stateful
        operator re-observe a run. Sources without random access leave this unimplemented."""
        raise NotImplementedError

    def frame_or_error(self, run: str, seq: int) -> SourceFrame:
        """`frame_at`, or an error frame when its files cannot be read (a missing or corrupt file):
        one bad frame is reported and skipped downstream, the stream goes on."""
        try:
            return self.frame_at(run, seq)
        except (OSError, ValueError) as exc:
            return SourceFrame(run, seq, 0, error=f"{type(exc).__name__}: {exc}")

    def total_frames(self) -> int | None:
        """How many frames `frames` will yield, when known up front (the launcher shows progress)."""
        return None

    def runs(self) -> dict[str, int] | None:
        """Every run and its number of frames, in `frames`' order, where `frame_at` reads any frame
        of them (a source may then send runs side by side: `runs_in_flight`); None otherwise."""
        return None


BUILTIN_KINDS = {
    "replayer": "umad_operators.replayer:Replayer",
    "world_model": "umad_operators.world_model:WorldModelPredictor",
    "difference": "umad_operators.difference:Difference",
    "fusion": "umad_operators.fusion:Fusion",
    "segmenter": "umad_operators.segmenter:Segmenter",
    "mask_refiner": "umad_operators.mask_refiner:MaskRefiner",
    "frame_result": "umad_operators.frame_result:FrameResult",
    "mnad": "umad_operators.mnad:MnadPredictor",
    "accumulator": "umad_operators.accumulator:Accumulator",
}


class UnknownOperatorError(LookupError):
    """graph.yaml names an operator kind or import path that cannot be loaded."""


def load_operator_class(kind: str | None = None, uses: str | None = None) -> type[Operator]:
    """Find an operator class by built-in kind or by `package.module:ClassName` import path."""
    target = uses or BUILTIN_KINDS.get(kind or "")
    if target is None:
        raise UnknownOperatorError(
            f"unknown operator kind {kind!r}; expected one of {sorted(BUILTIN_KINDS)} or `uses: pkg.module:Class`"
        )
    return import_class(target, Operator, "operator", UnknownOperatorError)
