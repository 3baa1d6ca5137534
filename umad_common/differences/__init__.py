"""Difference metrics (raw disagreement maps between the camera and the world model's picture of
it) and their normalisation to [0, 1]. Formulas: docs/design.md, "The method, per frame t".

    metric = build_metric("ssim", MetricOptions())
    raw = metric(target, recon, preds, pred_valid)      # (h, w) float32
    score = minmax(raw)                                   # or calibrated(raw, q)

A metric not in `METRICS` loads by import path: `build_metric("mypkg.mod:MyDifference", ...)`,
where `MyDifference` subclasses `DifferenceMetric`.
"""

from __future__ import annotations

from umad_common.dataflow.api.plugins import registered_class
from umad_common.differences.metrics import (
    ABOVE_RETURNS_ARRAY,
    AbsDifference,
    DifferenceInputError,
    DifferenceMetric,
    LidarDifference,
    MetricOptions,
    MseDifference,
    RangePairs,
    ShiftedSsimDifference,
    SsimDifference,
    TemporalDifference,
    above_returns,
    range_pairs,
    validate_frame,
)
from umad_common.differences.normalization import (
    Calibration,
    CalibrationError,
    CalibrationFitter,
    calibrated,
    load_calibration,
    minmax,
    robust,
)

METRICS: dict[str, type[DifferenceMetric] | str] = {
    "abs": AbsDifference,
    "mse": MseDifference,
    "ssim": SsimDifference,
    "ssim_shift": ShiftedSsimDifference,  # ours, not the paper's
    "perceptual": "umad_common.differences.perceptual:PerceptualDifference",  # torch: imported on use
    "temporal": TemporalDifference,
    "lidar": LidarDifference,  # ours: the lidar against the world model's lidar view
}


class UnknownMetricError(LookupError):
    """A metric name that is neither registered nor a loadable `package.module:Class` path."""


def metric_class(name: str) -> type[DifferenceMetric]:
    """The class for a registered name or a `package.module:ClassName` import path."""
    return registered_class(name, METRICS, DifferenceMetric, "metric", UnknownMetricError)


def build_metric(name: str, options: MetricOptions | None = None) -> DifferenceMetric:
    """Construct a metric by name or import path (weights load here, so bad files fail early)."""
    return metric_class(name).from_options(options or MetricOptions())


__all__ = [
    "ABOVE_RETURNS_ARRAY",
    "METRICS",
    "AbsDifference",
    "Calibration",
    "CalibrationError",
    "CalibrationFitter",
    "DifferenceInputError",
    "DifferenceMetric",
    "LidarDifference",
    "MetricOptions",
    "MseDifference",
    "RangePairs",
    "ShiftedSsimDifference",
    "SsimDifference",
    "TemporalDifference",
    "UnknownMetricError",
    "above_returns",
    "build_metric",
    "calibrated",
    "load_calibration",
    "metric_class",
    "minmax",
    "range_pairs",
    "robust",
    "validate_frame",
]
