"""Difference operator: one world-model frame in, one normalised disagreement map out.

Stateless (every frame carries its own past predictions), so `replicas: k` in graph.yaml splits
frames between k processes; `threads` keeps each replica's torch share of the cores small.

    diff_ssim:
      kind: difference
      inputs: {frame: world_model/frame}
      params: {metric: ssim, normalization: calibrated}
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from umad_common.dataflow import Context, Frame, Input, Operator, Output, input_array
from umad_common.differences import (
    METRICS,
    DifferenceMetric,
    MetricOptions,
    RangePairs,
    build_metric,
    calibrated,
    load_calibration,
    minmax,
    range_pairs,
    robust,
)
from umad_common.models.device import DeviceName, device_field

FRAME_ARRAYS = ("target", "recon", "preds", "pred_valid")


class Difference(Operator):
    """Computes one difference metric: a name in `umad_common.differences.METRICS` or an import path."""

    kind = "difference"
    inputs = (Input("frame"),)
    outputs = ("map",)

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

        metric: str = Field(
            "abs",
            description=f"{' | '.join(METRICS)}, or `package.module:Class` of a DifferenceMetric",
        )
        normalization: Literal["minmax", "robust", "calibrated"] = Field(
            "minmax",
            description="minmax: per frame to [0, 1] (paper); robust: z/(1+z), z = (r - median)/(P99.9 - median) "
            "per frame (ours); calibrated: r/(r+q) with q fitted on normal frames",
        )
        calibration: str = Field(
            "umad_common/assets/calibration.json",
            description="calibration JSON written by `umad calibrate` (used when normalization is calibrated)",
        )
        vgg_weights: str | None = Field(
            None,
            description="torchvision-format ImageNet VGG16 state dict file for the perceptual metric; "
            "when unset, the label-free feature net is used",
        )
        features: str = Field(
            "umad_common/assets/feature_net.safetensors",
            description="label-free feature net weights (safetensors + .json config) for the perceptual metric",
        )
        threads: int = Field(
            1, ge=1, le=64, description="torch CPU threads of this replica (the perceptual metric's network)"
        )
        device: DeviceName = device_field()

    @classmethod
    def input_paths(cls, params: BaseModel) -> dict[str, str]:
        paths = {}
        if params.metric == "perceptual":
            paths = {"vgg_weights": params.vgg_weights} if params.vgg_weights else {"features": params.features}
        if params.normalization == "calibrated":
            paths["calibration"] = params.calibration
        return paths

    def __init__(self, params: BaseModel | dict | None = None, context: Context | None = None):
        super().__init__(params, context)
        self.silent_runs: set[str] = set()  # runs whose lack of lidar returns was said already
        self._configure(self.params)

    def update_params(self, params: BaseModel) -> None:
        """Rebuild the metric and reload the calibration (a bad new file fails before anything changes)."""
        self._configure(params)
        self.params = params

    def _configure(self, params: Params) -> None:
        options = MetricOptions(
            vgg_weights=self.context.resolve(params.vgg_weights) if params.vgg_weights else None,
            features=self.context.resolve(params.features),
            threads=params.threads,
            device=params.device,
        )
        metric: DifferenceMetric = build_metric(params.metric, options)
        scale = None
        if params.normalization == "calibrated":
            path = self.context.resolve(params.calibration)
            scale = load_calibration(path).scale(metric.calibration_key, str(path))
        self.metric, self.scale = metric, scale

    def process(self, frame: Frame) -> dict[str, Output]:
        target, recon, preds, pred_valid = (input_array(frame, "frame", name, self.kind) for name in FRAME_ARRAYS)
        lidar = range_pairs(frame.inputs["frame"].arrays) if self.metric.needs_lidar else None
        if self.metric.needs_lidar and (lidar is None or len(lidar.range) == 0):
            return {"map": self.no_data(frame, target.shape[:2], lidar)}
        raw = self.metric(target, recon, preds, pred_valid, lidar=lidar)
        if self.params.normalization == "calibrated":
            score = calibrated(raw, self.scale)
        elif self.params.normalization == "robust":
            score = robust(raw)
        else:
            score = minmax(raw)
        meta = {"metric": self.params.metric, "normalization": self.params.normalization}
        if self.scale is not None:
            meta["calibration_scale"] = self.scale
        meta.update(self.metric.notes(pred_valid))
        arrays = {"map": np.ascontiguousarray(score, dtype=np.float32), **self.metric.side_arrays(score.shape, lidar)}
        return {"map": Output(arrays, meta)}

    def no_data(self, frame: Frame, shape: tuple[int, int], lidar: RangePairs | None) -> Output:
        """A lidar metric's frame without returns to compare: a map of zeros marked `no_data` (fusion and
        the sweep leave it out, as if the operator were absent), said in one line once per run."""
        reason = (
            "the world model sends no lidar returns (a model without a lidar head)"
            if lidar is None
            else "no lidar return lands in the camera's view (data without lidar)"
        )
        if frame.run not in self.silent_runs:
            self.silent_runs.add(frame.run)
            self.context.log.warning(
                "%s %s: %s; this map stays out of fusion, the camera maps carry on", self.kind, frame.frame_id, reason
            )
        meta = {"metric": self.params.metric, "normalization": self.params.normalization, "no_data": reason}
        return Output({"map": np.zeros(shape, np.float32)}, meta)
