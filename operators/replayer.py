"""Replayer: the graph's source. Publishes AnoVox scenarios (either layout) frame by frame.

One run per scenario folder (run = folder name), seq 0, 1, 2, ... over the sampled frames, stamps at
the recording's frame rate. Pacing (`lossless` with a window of unacked frames, or `realtime`) is
done by the runtime from the parameters declared here.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from umad_common.datasets.anovox import AnoVoxFrame, AnoVoxScenario, DatasetError, find_scenarios
from umad_common.operator import Context, Output, Source, SourceFrame

ROUTE_SHAPE = (192, 192)


class Replayer(Source):
    kind = "replayer"
    outputs = ("camera", "lidar", "ego", "route", "truth")

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

        source: str = Field(
            "data/synth/anomalous", description="a Scenario_* folder, or a folder searched recursively for them"
        )
        every: int = Field(1, ge=1, description="publish every k-th frame of each scenario")
        scenarios: list[str] | None = Field(None, description="keep only scenarios with these folder names (None: all)")
        max_frames: int | None = Field(
            None, ge=1, description="at most this many frames per run after sampling (None: all)"
        )
        pacing: Literal["lossless", "realtime"] = Field(
            "lossless", description="lossless: advance on acks; realtime: follow the stamps"
        )
        window: int = Field(8, ge=1, description="lossless pacing: frames in flight before waiting for acks")
        rate_hz: float = Field(10.0, gt=0, description="frame rate of the recording; stamps are frame index / rate_hz")

    def __init__(self, params: BaseModel | dict | None = None, context: Context | None = None):
        super().__init__(params, context)
        root = self.context.resolve(self.params.source)
        paths = find_scenarios(root)
        if self.params.scenarios is not None:
            wanted = set(self.params.scenarios)
            missing = sorted(wanted - {p.name for p in paths})
            if missing:
                raise DatasetError(f"{root}: scenarios {missing} not found; available: {sorted(p.name for p in paths)}")
            paths = [p for p in paths if p.name in wanted]
        if not paths:
            raise DatasetError(f"{root}: no AnoVox scenarios (Scenario_* folders with RGB-CAM... or RGB_IMG) found")
        self.scenarios = [AnoVoxScenario(p, every=self.params.every) for p in paths]

    def frames(self) -> Iterator[SourceFrame]:
        period_ns = 1e9 / self.params.rate_hz
        for scenario in self.scenarios:
            count = len(scenario) if self.params.max_frames is None else min(len(scenario), self.params.max_frames)
            for seq in range(count):
                frame = scenario[seq]
                stamp_ns = int(round(seq * scenario.every * period_ns))
                yield SourceFrame(scenario.name, seq, stamp_ns, frame_outputs(frame, scenario.name))


def frame_outputs(frame: AnoVoxFrame, scenario: str) -> dict[str, Output]:
    """The five topics of one frame; absent modalities become empty or zero arrays."""
    height, width = frame.rgb.shape[:2]
    lidar = frame.lidar if frame.lidar is not None else np.zeros((0, 4), np.float32)
    route = frame.route if frame.route is not None else np.zeros(ROUTE_SHAPE, np.uint8)
    instance = frame.instance if frame.instance is not None else np.zeros((height, width), np.int32)
    semantic = frame.semantic if frame.semantic is not None else np.zeros((height, width), np.uint8)
    return {
        "camera": Output({"rgb": frame.rgb}, {"frame_id": int(frame.frame_id), "scenario": scenario}),
        "lidar": Output({"points": np.ascontiguousarray(lidar, np.float32)}),
        "ego": Output({"ego": frame.ego.as_array()}),
        "route": Output({"route": np.ascontiguousarray(route, np.uint8)}),
        "truth": Output(
            {
                "anomaly": frame.anomaly.astype(np.uint8),
                "instance": instance.astype(np.int32),
                "semantic": semantic.astype(np.uint8),
            }
        ),
    }
