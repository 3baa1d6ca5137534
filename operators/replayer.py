"""Replayer: the graph's source. Publishes drives frame by frame: AnoVox scenarios (either layout),
ROS 2 bags and Foxglove MCAP recordings (`umad_common.datasets.drive`), or an MCAP log of an earlier
run, byte for byte.

One run per drive (run = the drive's name: its folder, or a bare recording's file name), seq 0, 1,
2, ... over the sampled frames. Stamps: a recording's own (its camera messages' log times); AnoVox's
10 Hz (frame index x 100 ms, so sampling keeps real time). Pacing (`lossless` with a window of unacked
frames, or `realtime`) is done by the runtime from the `SourceParams` fields.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from pydantic import BaseModel, Field

from umad_common.dataflow import Context, Output, Source, SourceFrame, SourceParams
from umad_common.dataflow.record.log_source import recorded_frame, recorded_frames
from umad_common.datasets.drive import UMAD_LOG_PROFILE, DatasetError, Drive, DriveFrame, drive_name, mcap_profile
from umad_common.datasets.formats import find_drives, open_drive

ROUTE_SHAPE = (192, 192)


class Replayer(Source):
    kind = "replayer"
    outputs = ("camera", "lidar", "ego", "route", "truth")

    class Params(SourceParams):
        source: str = Field(
            "data/synthetic/anomalous",
            description="drives: an AnoVox Scenario_* folder, a ROS 2 bag (rosbag2 folder, .mcap or .db3), an MCAP "
            "with Foxglove schemas, or a folder searched for them; or an MCAP log of an earlier run",
        )
        topics: str | None = Field(
            None,
            description="recordings: the topic of each role, `camera=/a,lidar=/b,odometry=/c,control=/d,labels=/e`; "
            "roles not named are chosen by type (`umad data info` shows the choice)",
        )
        allow_truncated: bool = Field(False, description="read a recording cut off by a crash up to the damage")
        every: int = Field(1, ge=1, description="publish every k-th frame of each scenario")
        score_every: int = Field(
            1,
            ge=1,
            description="score every k-th published frame (seq % k == 0); the others carry meta `skip`: the "
            "world model still steps on them, every other operator passes them on without computing",
        )
        scenarios: list[str] | None = Field(None, description="keep only the drives with these names (None: all)")
        max_frames: int | None = Field(
            None, ge=1, description="at most this many frames per run after sampling (None: all)"
        )

    @classmethod
    def input_paths(cls, params: BaseModel) -> dict[str, str]:
        return {"source": params.source}

    def __init__(self, params: BaseModel | dict | None = None, context: Context | None = None):
        super().__init__(params, context)
        root = self.context.resolve(self.params.source)
        is_log = root.suffix == ".mcap" and (not root.is_file() or mcap_profile(root) == UMAD_LOG_PROFILE)
        self.log_path = root if is_log else None
        self.scenarios: dict[str, Drive] = {}
        self._run_cache: dict = {}  # an MCAP log source: the frames of the run a rewind asked for
        if self.log_path is not None:
            if not root.is_file():
                raise DatasetError(f"{root}: MCAP log not found")
            return
        paths = find_drives(root)
        if self.params.scenarios is not None:
            wanted = set(self.params.scenarios)
            missing = sorted(wanted - {drive_name(p) for p in paths})
            if missing:
                raise DatasetError(f"{root}: drives {missing} not found; available: {sorted(map(drive_name, paths))}")
            paths = [p for p in paths if drive_name(p) in wanted]
        if not paths:
            raise DatasetError(
                f"{root}: no drives found; expected AnoVox Scenario_* folders, ROS 2 bags or Foxglove MCAP recordings"
            )
        names = [drive_name(p) for p in paths]
        if len(set(names)) != len(names):
            twice = sorted({n for n in names if names.count(n) > 1})
            raise DatasetError(
                f"{root}: drive names {twice} occur more than once; runs are named by drive, so point at one copy"
            )
        p = self.params
        for path in paths:
            drive = open_drive(path, p.every, p.topics, allow_truncated=p.allow_truncated)
            self.scenarios[drive.name] = drive
            for note in drive.notes():
                self.context.log.info("replayer: drive %s: %s", drive.name, note)

    def run_length(self, run: str) -> int:
        """Frames published for a run (after sampling and max_frames)."""
        scenario = self.scenarios[run]
        return len(scenario) if self.params.max_frames is None else min(len(scenario), self.params.max_frames)

    def total_frames(self) -> int | None:
        return None if self.log_path is not None else sum(self.run_length(run) for run in self.scenarios)

    def runs(self) -> dict[str, int] | None:
        return None if self.log_path is not None else {run: self.run_length(run) for run in self.scenarios}

    def frames(self) -> Iterator[SourceFrame]:
        if self.log_path is not None:  # a recorded run: its payloads again, byte for byte
            yield from recorded_frames(self.log_path, self.context.graph_name, self.context.op_id, self.outputs)
            return
        for run in self.scenarios:
            for seq in range(self.run_length(run)):
                yield self.frame_or_error(run, seq)

    def frame_at(self, run: str, seq: int) -> SourceFrame:
        """Frame `seq` of scenario `run`, read again from disk (identical to what `frames` yields)."""
        if self.log_path is not None:
            c = self.context
            return recorded_frame(self.log_path, c.graph_name, c.op_id, self.outputs, run, seq, self._run_cache)
        if run not in self.scenarios:
            raise KeyError(f"run {run!r} is not one of this replayer's scenarios {sorted(self.scenarios)}")
        if not 0 <= seq < self.run_length(run):
            raise IndexError(f"seq {seq} out of range for run {run!r} with {self.run_length(run)} frames")
        drive = self.scenarios[run]
        scored = seq % self.params.score_every == 0
        return SourceFrame(run, seq, drive.stamp_ns(seq), frame_outputs(drive[seq], run, drive.sensors, scored))


def frame_outputs(
    frame: DriveFrame, scenario: str, sensors: dict | None = None, scored: bool = True
) -> dict[str, Output]:
    """The five topics of one frame; absent modalities become empty or zero arrays. `sensors` (the
    drive's rig, see `umad_common.datasets.sensor_rig`) travels as the lidar's meta `sensors`. A
    frame that is not scored carries meta `skip` on every topic and no labels."""
    height, width = frame.rgb.shape[:2]
    lidar = frame.lidar if frame.lidar is not None else np.zeros((0, 4), np.float32)
    route = frame.route if frame.route is not None else np.zeros(ROUTE_SHAPE, np.uint8)
    instance = frame.instance if frame.instance is not None else np.zeros((height, width), np.int32)
    semantic = frame.semantic if frame.semantic is not None else np.zeros((height, width), np.uint8)
    skip = {} if scored else {"skip": True}
    truth = {
        "anomaly": frame.anomaly.astype(np.uint8),
        "instance": instance.astype(np.int32),
        "semantic": semantic.astype(np.uint8),
    }
    return {
        "camera": Output({"rgb": frame.rgb}, {"frame_id": int(frame.frame_id), "scenario": scenario, **skip}),
        "lidar": Output(
            {"points": np.ascontiguousarray(lidar, np.float32)}, {**skip, **({"sensors": sensors} if sensors else {})}
        ),
        "ego": Output({"ego": frame.ego.as_array()}, skip),
        "route": Output({"route": np.ascontiguousarray(route, np.uint8)}, skip),
        "truth": Output(truth if scored else {}, skip),
    }
