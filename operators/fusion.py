"""Fusion: one anomaly map per frame from every live difference map, as a weighted mean.

Input `maps` is a wildcard port (e.g. `diff_*/map`): the runtime hands over whatever producers are
live for the frame, waiting for all expected ones up to `deadline_ms` in live mode and always in
lossless mode. A metric that joins or leaves mid-stream is fused in or out from that frame on; new
weights set through the control key (`umad set fusion.weights.ssim=0.5`) apply from the next frame.
A map marked `no_data` (the lidar difference of a frame without lidar returns) is left out the same way.
With `above_lidar_weight` below 1, the other maps count that much at the pixels the lidar map marks
`above_returns` (the sky and what the lidar's beams do not reach; ours). With `lidar_camera_exponent`
above 0, that map (the lidar's) then counts where the other maps disagree too (ours).
The arithmetic (and the rule for absent metrics) is `umad_common.refine.fuse`.
"""

from __future__ import annotations

from pydantic import Field, field_validator

from umad_common.dataflow import Frame, Input, JoinParams, Operator, Output, input_array
from umad_common.dataflow.api.messages import Message
from umad_common.differences import ABOVE_RETURNS_ARRAY
from umad_common.refine import fuse, scale_by_camera_agreement, used_weights, weigh_down_above_lidar

DEFAULT_WEIGHTS = {"abs": 0.2, "mse": 0.2, "ssim": 0.2, "perceptual": 0.2, "temporal": 0.2}  # difference `metric` names


class FusionParams(JoinParams):
    weights: dict[str, float] = Field(
        default_factory=lambda: dict(DEFAULT_WEIGHTS),
        description="weight in [0, 1] per metric name (a difference map's meta 'metric', else its producer id); "
        "maps of metrics without a weight, or with weight 0, are not fused; the fused map is the weighted "
        "mean over the metrics present in the frame",
    )

    @field_validator("weights")
    @classmethod
    def _weights_in_unit_interval(cls, weights: dict[str, float]) -> dict[str, float]:
        for metric, weight in weights.items():
            if not 0.0 <= weight <= 1.0:
                raise ValueError(f"weight of metric {metric!r} is {weight}; expected a value in [0, 1]")
        return weights

    above_lidar_weight: float = Field(
        1.0,
        ge=0.0,
        le=1.0,
        description="factor on every other map at the pixels a map marks `above_returns` (the lidar difference: "
        "above every lidar return near the column, the sky and what the beams do not reach); 1 leaves the maps "
        "as they are (the paper's fusion)",
    )
    lidar_camera_exponent: float = Field(
        0.0,
        ge=0.0,
        le=4.0,
        description="the map that marks `above_returns` (the lidar difference's) times the other maps' weighted mean, "
        "scaled to its frame maximum, to this power, then rescaled to [0, 1]: lidar evidence counts where the camera "
        "maps disagree too (a parked car the lidar head does not draw, the camera model does); 0 leaves it as it is",
    )


def metric_of(producer: str, msg: Message) -> str:
    """The metric a difference map measures: its meta 'metric', else the producing operator's id."""
    return str(msg.meta.get("metric") or producer)


class Fusion(Operator):
    """Weighted mean of the difference maps of a frame; records the metrics and weights it used."""

    kind = "fusion"
    inputs = (Input("maps", many=True),)
    outputs = ("fused",)
    Params = FusionParams

    def process(self, frame: Frame) -> dict[str, Output]:
        received = frame.many.get("maps", {})
        if not received:
            raise ValueError(f"fusion {frame.frame_id}: no difference maps in input 'maps'; expected at least one")
        maps = {}
        above = None  # (metric, mask): the map that marks the pixels above the lidar's returns
        for producer in sorted(received):
            msg = received[producer]
            if msg.meta.get("no_data"):
                continue  # nothing measured (a lidar map without returns): fused as if absent
            metric = metric_of(producer, msg)
            if metric in maps:
                raise ValueError(
                    f"fusion {frame.frame_id}: two producers report metric {metric!r} "
                    f"({sorted(p for p in received if metric_of(p, received[p]) == metric)}); expected one map per metric"
                )
            maps[metric] = input_array(frame, "maps", "map", self.kind, producer)
            if ABOVE_RETURNS_ARRAY in msg.arrays:
                above = (metric, input_array(frame, "maps", ABOVE_RETURNS_ARRAY, self.kind, producer))
        weights = self.params.weights
        if above is not None:
            maps = weigh_down_above_lidar(maps, above[1], above[0], self.params.above_lidar_weight)
            maps = scale_by_camera_agreement(maps, above[0], weights, self.params.lidar_camera_exponent)
        fused = fuse(maps, weights)
        used = used_weights(set(maps), weights)
        meta = {
            "metrics": list(used),
            "weights": used,
            "ignored": sorted(set(maps) - set(used)),
            "partial": bool(frame.partial),
        }
        if above is not None:
            meta["above_lidar_weight"] = self.params.above_lidar_weight
            meta["lidar_camera_exponent"] = self.params.lidar_camera_exponent
        return {"fused": Output({"map": fused}, meta)}
