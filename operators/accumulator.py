"""Accumulator: the evaluation sink. Pools every score map's pixels against the ground truth and
publishes per-run and overall AP, FPR95 and AUROC while the stream runs.

Input `scores` is a wildcard port (e.g. `fusion/fused`, `refine_*/refined`, `mnad/map`): each
producer is scored separately. Labels (`replayer/truth` `anomaly`, 0/1/255) are resized
nearest-neighbour to each score map's shape. Memory is O(1) in the number of pixels
(`umad_common.metrics.PixelMetrics`: two 65,536-bin histograms per producer and run).

A retransmitted frame is counted once: each (producer, run, seq) enters the histograms only the
first time; a duplicate re-publishes the current metrics without changing them.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from umad_common.dataflow import Frame, Input, Operator, Output, input_array
from umad_common.metrics.pixel import PixelMetrics
from umad_common.refine import resize_nearest

REPORTED = ("AP", "FPR95", "AUROC", "n_anomaly", "n_normal", "n_ignored")


class AccumulatorParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    out: str | None = Field(
        default=None,
        description="optional JSON file (relative to the graph folder unless absolute) rewritten at the end of "
        "every run with each finished run's metrics and the overall metrics so far",
    )
    every: int = Field(
        default=1,
        ge=1,
        description="publish the running metrics every `every` frames of a run (1 = every frame)",
    )


def summarise(metrics: PixelMetrics) -> dict[str, Any]:
    """AP, FPR95, AUROC and pixel counts; undefined values (no anomaly pixel yet) become None."""
    result = metrics.compute()
    return {k: (None if isinstance(result[k], float) and math.isnan(result[k]) else result[k]) for k in REPORTED}


class Accumulator(Operator):
    """Pooled pixel metrics per score producer, per run and over all runs."""

    kind = "accumulator"
    inputs = (Input("scores", many=True), Input("truth"))
    outputs = ("metrics",)
    Params = AccumulatorParams

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        self.per_run: dict[str, dict[str, PixelMetrics]] = {}  # run -> producer -> metrics
        self.overall: dict[str, PixelMetrics] = {}  # producer -> metrics
        self.frames_seen: dict[str, int] = {}  # run -> frames with at least one new map
        self.counted: set[tuple[str, str, int]] = set()  # (producer, run, seq) already in the histograms
        self.finished: dict[str, dict[str, dict[str, Any]]] = {}  # run -> producer -> final metrics
        if self.params.out is not None:
            out = self.context.resolve(self.params.out)
            if out.exists() and out.is_dir():
                raise ValueError(
                    f"accumulator: out={self.params.out!r} resolves to the folder {out}; expected a file path"
                )

    def process(self, frame: Frame) -> dict[str, Output]:
        labels = input_array(frame, "truth", "anomaly", self.kind)
        if labels.ndim != 2:
            raise ValueError(f"accumulator {frame.frame_id}: truth 'anomaly' has shape {labels.shape}; expected (H, W)")
        received = frame.many.get("scores", {})
        new = False
        for producer in sorted(received):
            key = (producer, frame.run, frame.seq)
            if key in self.counted:
                continue
            score_map = input_array(frame, "scores", "map", self.kind, producer)
            if score_map.ndim != 2:
                raise ValueError(
                    f"accumulator {frame.frame_id}: map from {producer!r} has shape {score_map.shape}; expected (h, w)"
                )
            resized = resize_nearest(labels, score_map.shape)
            run_metrics = self.per_run.setdefault(frame.run, {}).setdefault(producer, PixelMetrics())
            run_metrics.update(score_map, resized)
            self.overall.setdefault(producer, PixelMetrics()).update(score_map, resized)
            self.counted.add(key)
            new = True
        if new:
            self.frames_seen[frame.run] = self.frames_seen.get(frame.run, 0) + 1
            if self.frames_seen[frame.run] % self.params.every != 0:
                return {}
        return {"metrics": Output(meta=self.snapshot(frame.run, final=False))}

    def snapshot(self, run: str, final: bool) -> dict[str, Any]:
        """The metrics message: this run's and the overall metrics per producer."""
        return {
            "run": run,
            "final": final,
            "frames": self.frames_seen.get(run, 0),
            "per_run": {p: summarise(m) for p, m in sorted(self.per_run.get(run, {}).items())},
            "overall": {p: summarise(m) for p, m in sorted(self.overall.items())},
        }

    def end_run(self, run: str) -> dict[str, Output]:
        meta = self.snapshot(run, final=True)
        self.finished[run] = meta["per_run"]
        self.per_run.pop(run, None)  # the overall histograms keep its pixels
        if self.params.out is not None:
            self.write_json(self.context.resolve(self.params.out), meta["overall"])
        return {"metrics": Output(meta=meta)}

    def write_json(self, path: Path, overall: dict[str, Any]) -> None:
        """Atomically rewrite the results file (a reader never sees half a file)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps({"runs": self.finished, "overall": overall}, indent=2, allow_nan=False))
        tmp.replace(path)
