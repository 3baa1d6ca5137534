"""Normalising raw difference maps to [0, 1]: per frame (`minmax`, `robust`) or by a fitted scale (`calibrated`).

`minmax` is the paper's rule: (r - min) / (max - min) over the frame, all zeros for a constant map.
It makes every frame reach 1, normal or not, so scores are not comparable across frames: one
extreme pixel (a facade, the sky in light the model rarely saw) sets the whole frame's scale.

`robust` (ours) measures each pixel against the frame's bulk instead of its extreme::

    score = z / (1 + z),   z = max(r - median(r), 0) / (P99.9(r) - median(r))

over the frame's pixels (all zeros when P99.9 = median). The median is what the frame's normal
pixels mostly show and P99.9 what its hardest normal region reaches, so the score is near 0.5 at
the frame's own 99.9th percentile, whatever its light, and an obstacle k times further above the
median than that scores k / (1 + k). Median and percentile move with any positive affine change of
r, so `robust(minmax(r))` equals `robust(r)` (up to float rounding): the sweep derives it from a
log recorded with `minmax`.

`calibrated` maps each metric through one scale q fitted on NORMAL frames only (`umad calibrate`)::

    score = r' / (r' + q),   r' = max(r, 0),   q = the 99.9th percentile of r over all normal pixels

so a normal frame's scores stay mostly below 0.5 (99.9 % of normal pixels do), an anomaly several
times q approaches 1 (reached only by float32 rounding, r > ~1e7 q): nothing is forced to 1 and,
unlike clipping at q, the order of the strongest responses is kept (no ties at the top, which AP would pay for). Every
metric's q lands on the same 0.5, so fused metrics are on a common scale.

The calibration file (JSON, stored beside the model files) holds q per calibration key plus how it
was made; keys are the metrics' `calibration_key`s: their names in `METRICS`, `perceptual/vgg16`
for the ImageNet extractor, and a user's own metric's `name` (else its class name).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROBUST_PERCENTILE = 99.9  # chosen on validation seed 2 and the stress set among 90, 99, 99.9 (docs/experiments.md)
CALIBRATION_VERSION = 1
CALIBRATION_PERCENTILE = 99.9
CALIBRATION_RULE = "score = r / (r + q), r = max(raw, 0), q = 99.9th percentile of raw values over normal pixels"


class CalibrationError(ValueError):
    """A calibration file is missing, malformed or lacks the metric asked for."""


def minmax(raw: np.ndarray) -> np.ndarray:
    """(r - min) / (max - min) per frame; a constant (or empty) map gives zeros."""
    raw = np.asarray(raw, dtype=np.float32)
    if raw.size == 0:
        return raw.copy()
    lo, hi = float(raw.min()), float(raw.max())
    if not hi > lo:
        return np.zeros_like(raw)
    return ((raw - lo) / (hi - lo)).astype(np.float32)


def robust(raw: np.ndarray, percentile: float = ROBUST_PERCENTILE) -> np.ndarray:
    """z / (1 + z), z = (r - median) / (P_percentile - median) clipped at 0, per frame; zeros when
    the percentile equals the median (a constant or empty map)."""
    raw = np.asarray(raw, dtype=np.float32)
    if raw.size == 0:
        return raw.copy()
    median, high = np.percentile(raw, [50.0, percentile])
    if not high > median:
        return np.zeros_like(raw)
    z = np.maximum(raw - np.float32(median), 0.0) / np.float32(high - median)
    return (z / (1.0 + z)).astype(np.float32)


def calibrated(raw: np.ndarray, q: float) -> np.ndarray:
    """r' / (r' + q) with r' = max(r, 0): order-preserving, q -> 0.5, in [0, 1]."""
    if not q > 0:
        raise CalibrationError(f"calibration scale must be > 0, got {q}")
    r = np.maximum(np.asarray(raw, dtype=np.float32), 0.0)
    return (r / (r + np.float32(q))).astype(np.float32)


@dataclass
class Calibration:
    """Per-metric scales q and the provenance of the fit."""

    scales: dict[str, float]
    info: dict[str, Any] = field(default_factory=dict)
    stats: dict[str, dict[str, float]] = field(default_factory=dict)

    def scale(self, key: str, source: str = "calibration") -> float:
        """The q of one calibration key; raises CalibrationError listing the keys the file has."""
        if key not in self.scales:
            raise CalibrationError(
                f"{source}: no scale for metric {key!r}; the file has {sorted(self.scales)} "
                "(run `umad calibrate` with the same world model and feature files)"
            )
        return self.scales[key]

    def to_json(self) -> dict[str, Any]:
        return {
            "version": CALIBRATION_VERSION,
            "rule": CALIBRATION_RULE,
            "percentile": CALIBRATION_PERCENTILE,
            "scales": self.scales,
            "stats": self.stats,
            "info": self.info,
        }

    def save(self, path: str | Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_json(), indent=2) + "\n")


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration JSON; raises CalibrationError naming the file and what was expected."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file not found (make one with `umad calibrate`)")
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot read calibration JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("version") != CALIBRATION_VERSION:
        raise CalibrationError(f"{path}: expected a calibration object with version {CALIBRATION_VERSION}")
    scales = data.get("scales")
    if not isinstance(scales, dict) or not all(isinstance(v, int | float) and v > 0 for v in scales.values()):
        raise CalibrationError(f"{path}: expected 'scales' mapping metric -> positive number, got {scales!r}")
    return Calibration({k: float(v) for k, v in scales.items()}, data.get("info", {}), data.get("stats", {}))


class CalibrationFitter:
    """Collects raw maps of normal frames per calibration key and fits each key's q."""

    def __init__(self, percentile: float = CALIBRATION_PERCENTILE) -> None:
        self.percentile = percentile
        self.values: dict[str, list[np.ndarray]] = {}

    def add(self, key: str, raw: np.ndarray) -> None:
        self.values.setdefault(key, []).append(np.asarray(raw, dtype=np.float32).ravel())

    def fit(self, info: dict[str, Any] | None = None) -> Calibration:
        """q = the percentile of all collected values; raises if a key has no positive value there."""
        scales: dict[str, float] = {}
        stats: dict[str, dict[str, float]] = {}
        for key, chunks in sorted(self.values.items()):
            values = np.concatenate(chunks)
            q = float(np.percentile(values, self.percentile))
            if not q > 0:
                raise CalibrationError(
                    f"{key}: the {self.percentile}th percentile of normal values is {q}; cannot scale"
                )
            scales[key] = q
            stats[key] = {
                "frames": len(chunks),
                "pixels": int(values.size),
                "p50": float(np.percentile(values, 50)),
                "p99": float(np.percentile(values, 99)),
                "max": float(values.max()),
            }
        return Calibration(scales, dict(info or {}), stats)
