"""Tiny operators for runtime tests: a counting source, two transforms, a joining sink that logs."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from umad_common.operator import Input, Operator, Output, Source, SourceFrame


class CounterSource(Source):
    kind = "toy_counter"
    outputs = ("value",)

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        runs: int = 1
        frames: int = 20
        size: int = 4  # float32 elements per frame
        window: int = 4
        ack_timeout_s: float = 3.0
        pacing: str = "lossless"

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
        fail_on_seq: int = -1

    def process(self, frame):
        if frame.seq == self.params.fail_on_seq:
            raise RuntimeError("asked to fail")
        time.sleep(self.params.delay_s)
        return {"y": Output({"x": frame.inputs["x"].arrays["x"] * self.params.factor}, {"pid": os.getpid()})}


class JoinSink(Operator):
    """Sums its single input with every map of its wildcard input; logs one JSON line per frame."""

    kind = "toy_sink"
    inputs = (Input("a"), Input("b", many=True))
    outputs = ("total",)

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        log: str = ""

    def process(self, frame):
        a = frame.inputs["a"].arrays["x"]
        total = a + sum(m.arrays["x"] for m in frame.many["b"].values())
        self._write({"run": frame.run, "seq": frame.seq, "total": float(total[0]), "producers": sorted(frame.many["b"])})
        return {"total": Output({"x": total})}

    def end_run(self, run):
        self._write({"run": run, "end": True})
        return {}

    def _write(self, obj):
        if self.params.log:
            with Path(self.params.log).open("a") as f:
                f.write(json.dumps(obj) + "\n")
