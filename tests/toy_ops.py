"""Tiny operators for runtime tests: a counting source, two transforms, a joining sink that logs."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from umad_common.dataflow import Input, Operator, Output, Source, SourceFrame, SourceParams


class CounterSource(Source):
    kind = "toy_counter"
    outputs = ("value",)

    class Params(SourceParams):
        runs: int = 1
        frames: int = 20
        size: int = 4  # float32 elements per frame
        window: int = 4
        ack_timeout_s: float = 3.0

    def frames(self):
        for r in range(self.params.runs):
            for seq in range(self.params.frames):
                value = np.full(self.params.size, float(seq + 1000 * r), dtype=np.float32)
                yield SourceFrame(f"run{r}", seq, seq * 100_000_000, {"value": Output({"x": value})})


class Scale(Operator):
    kind = "toy_scale"
    inputs = (Input("x"),)
    outputs = ("y",)

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        factor: float = 2.0
        delay_s: float = 0.0
        first_delay_s: float = 0.0  # the first frame's extra time, as an operator's start-up
        fail_on_seq: int = -1

    started = False

    def update_params(self, params):
        """Refuses a change the schema accepts, as an operator whose new weight file does not load."""
        if params.factor == 0:
            raise ValueError("a factor of 0 is refused")
        super().update_params(params)

    def process(self, frame):
        if frame.seq == self.params.fail_on_seq:
            raise RuntimeError("asked to fail")
        time.sleep(self.params.delay_s + (self.params.first_delay_s if not self.started else 0.0))
        self.started = True
        return {"y": Output({"x": frame.inputs["x"].arrays["x"] * self.params.factor}, {"pid": os.getpid()})}


class JoinSink(Operator):
    """Sums its single input with every map of its wildcard input; logs one JSON line per frame."""

    kind = "toy_sink"
    inputs = (Input("a"), Input("b", many=True))
    outputs = ("total",)

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        log: str = ""
        silent: bool = False  # publish nothing: an operator that declares more outputs than it returns

    def process(self, frame):
        a = frame.inputs["a"].arrays["x"]
        total = a + sum(m.arrays["x"] for m in frame.many["b"].values())
        self._write(
            {"run": frame.run, "seq": frame.seq, "total": float(total[0]), "producers": sorted(frame.many["b"])}
        )
        return {} if self.params.silent else {"total": Output({"x": total})}

    def end_run(self, run):
        self._write({"run": run, "end": True})
        return {}

    def _write(self, obj):
        if self.params.log:
            with Path(self.params.log).open("a") as f:
                f.write(json.dumps(obj) + "\n")


def _counter_frame(run_index: int, seq: int, size: int) -> SourceFrame:
    value = np.full(size, float(seq + 1000 * run_index), dtype=np.float32)
    return SourceFrame(f"run{run_index}", seq, seq * 100_000_000, {"value": Output({"x": value})})


class RewindableCounterSource(CounterSource):
    """A counter source with random access, so a restarted ordered operator can re-observe a run."""

    kind = "toy_rewindable_counter"

    def frames(self):
        for r in range(self.params.runs):
            for seq in range(self.params.frames):
                yield _counter_frame(r, seq, self.params.size)

    def frame_at(self, run, seq):
        return _counter_frame(int(run[3:]), seq, self.params.size)

    def runs(self):
        return {f"run{r}": self.params.frames for r in range(self.params.runs)}


class RunningSum(Operator):
    """Stateful: the sum of all values of the run so far (needs every earlier frame, in order), each
    run its own; its outputs name the process that made them (meta `pid`)."""

    kind = "toy_running_sum"
    inputs = (Input("x"),)
    outputs = ("y",)
    ordered = True

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        delay_s: float = 0.0

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        self.totals: dict[str, float] = {}  # run -> its sum so far

    def process(self, frame):
        total = (0.0 if frame.seq == 0 else self.totals[frame.run]) + float(frame.inputs["x"].arrays["x"][0])
        time.sleep(self.params.delay_s)
        self.totals[frame.run] = total
        return {"y": Output({"x": np.array([total], np.float32)}, {"pid": os.getpid()})}

    def end_run(self, run):
        self.totals.pop(run, None)
        return {}


class Logger(Operator):
    kind = "toy_logger"
    inputs = (Input("x"),)
    outputs = ()

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        log: str = ""

    def process(self, frame):
        with Path(self.params.log).open("a") as f:
            x = frame.inputs["x"]
            line = {"run": frame.run, "seq": frame.seq, "value": float(x.arrays["x"][0]), "pid": x.meta.get("pid")}
            f.write(json.dumps(line) + "\n")
        return {}


class ImageStats(Operator):
    """Per frame, the mean and max of one image array: a light sink for graphs with the real replayer."""

    kind = "toy_image_stats"
    inputs = (Input("image"),)
    outputs = ("stats",)

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        scale: float = 1.0

    def process(self, frame):
        rgb = frame.inputs["image"].arrays["rgb"].astype(np.float32)
        return {"stats": Output({"x": np.array([rgb.mean(), rgb.max()], np.float32) * self.params.scale})}


class LossyPairSource(CounterSource):
    """A counter source with a second output, `extra`, left out at the seqs in `lose_extra`: to an
    operator that joins both, those frames lose a payload on the way."""

    kind = "toy_lossy_pair"
    outputs = ("value", "extra")

    class Params(CounterSource.Params):
        lose_extra: list[int] = []

    def frames(self):
        for frame in super().frames():
            if frame.seq not in self.params.lose_extra:
                frame.outputs["extra"] = frame.outputs["value"]
            yield frame


class SlowOrdered(Operator):
    """Ordered and slow: joins `x` and `extra`, takes `delay_s`, logs the frame and passes `x` on."""

    kind = "toy_slow_ordered"
    inputs = (Input("x"), Input("extra"))
    outputs = ("y",)
    ordered = True

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        delay_s: float = 0.0
        log: str = ""

    def process(self, frame):
        time.sleep(self.params.delay_s)
        with Path(self.params.log).open("a") as f:
            f.write(json.dumps({"run": frame.run, "seq": frame.seq}) + "\n")
        return {"y": Output({"x": frame.inputs["x"].arrays["x"]})}
