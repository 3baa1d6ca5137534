"""The pixel difference metrics of UMAD: one small class per formula (docs/design.md, "The method, per frame t").

Every metric turns one world-model frame (the camera image x, the reconstruction x̂_t and the past
predictions x̂_{t|t-i}) into a raw (h, w) float32 disagreement map, larger = more unexpected.
Normalisation to [0, 1] is a separate step (`umad_common.differences.normalization`).

A new metric is one subclass of `DifferenceMetric` with a `compute` method; register it in
`umad_common.differences.METRICS` or name it by import path (`metric: mypkg.mod:MyDifference`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, NamedTuple, NoReturn

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt, minimum_filter1d


class DifferenceInputError(ValueError):
    """A frame array handed to a difference metric has the wrong dtype or shape."""


@dataclass(frozen=True)
class MetricOptions:
    """What a metric may need beyond the frame: weight files (already resolved to absolute paths), and
    the CPU threads and the device (`umad_common.models.device`) of a metric that runs a network."""

    vgg_weights: Path | None = None
    features: Path | None = None
    threads: int = 1
    device: str = "cpu"


def validate_frame(target: np.ndarray, recon: np.ndarray, preds: np.ndarray, pred_valid: np.ndarray) -> tuple[int, int]:
    """Check the world model's frame arrays against the `frame` contract; return (h, w).

    Raises:
        DifferenceInputError: naming the array, what was expected and what it got.
    """

    def fail(name: str, expected: str, arr: Any) -> NoReturn:
        got = f"{arr.dtype} {tuple(arr.shape)}" if isinstance(arr, np.ndarray) else type(arr).__name__
        raise DifferenceInputError(f"{name}: expected {expected}, got {got}")

    if not (
        isinstance(target, np.ndarray) and target.dtype == np.float32 and target.ndim == 3 and target.shape[2] == 3
    ):
        fail("target", "float32 array of shape (h, w, 3)", target)
    h, w = target.shape[:2]
    if not (isinstance(recon, np.ndarray) and recon.dtype == np.float32 and recon.shape == (h, w, 3)):
        fail("recon", f"float32 array of shape ({h}, {w}, 3) like target", recon)
    if not (
        isinstance(preds, np.ndarray) and preds.dtype == np.float32 and preds.ndim == 4 and preds.shape[1:] == (h, w, 3)
    ):
        fail("preds", f"float32 array of shape (n, {h}, {w}, 3)", preds)
    n = preds.shape[0]
    if not (isinstance(pred_valid, np.ndarray) and pred_valid.dtype == np.uint8 and pred_valid.shape == (n,)):
        fail("pred_valid", f"uint8 array of shape ({n},) like preds' first axis", pred_valid)
    return h, w


RANGE_PAIR_ARRAYS = ("lidar_pixel", "lidar_range", "lidar_expected")  # `RangePairs`' arrays in a `frame`
EXPECTED_HEIGHT_ARRAY = "lidar_expected_height"  # its optional fourth (a frame of an older world model lacks it)
ABOVE_RETURNS_ARRAY = "above_returns"  # the lidar map message's (h, w) uint8: 1 above every return near the column


class RangePairs(NamedTuple):
    """Each lidar return in the camera's view (the world model's frame arrays of the same names): its
    pixel, the range measured, the range the world model's lidar view expected there and, where the
    frame has it, the height above the ground of the point expected."""

    pixel: np.ndarray  # (N, 2) int32 (row, column) in the target image
    range: np.ndarray  # (N,) float32 metres measured
    expected: np.ndarray  # (N,) float32 metres expected
    expected_height: np.ndarray | None = None  # (N,) float32 metres above the vehicle's origin


def range_pairs(arrays: dict[str, np.ndarray]) -> RangePairs | None:
    """The lidar arrays of a world-model frame's `arrays`, or None where the frame has none (a world
    model without a lidar head)."""
    if not all(name in arrays for name in RANGE_PAIR_ARRAYS):
        return None
    return RangePairs(*(arrays[name] for name in RANGE_PAIR_ARRAYS), arrays.get(EXPECTED_HEIGHT_ARRAY))


def validate_range_pairs(pairs: RangePairs, shape: tuple[int, int]) -> RangePairs:
    """Check the lidar arrays against the `frame` contract and the image's (h, w).

    Raises:
        DifferenceInputError: naming the array, what was expected and what it got.
    """
    pixel, measured, expected = (np.asarray(a) for a in pairs[:3])
    n = len(measured)
    if pixel.dtype != np.int32 or pixel.shape != (n, 2):
        raise DifferenceInputError(
            f"lidar_pixel: expected int32 array of shape ({n}, 2), got {pixel.dtype} {pixel.shape}"
        )
    heights = [] if pairs.expected_height is None else [(EXPECTED_HEIGHT_ARRAY, np.asarray(pairs.expected_height))]
    for name, values in (("lidar_range", measured), ("lidar_expected", expected), *heights):
        if values.dtype != np.float32 or values.shape != (n,):
            raise DifferenceInputError(
                f"{name}: expected float32 array of shape ({n},), got {values.dtype} {values.shape}"
            )
    if n and (pixel.min() < 0 or pixel[:, 0].max() >= shape[0] or pixel[:, 1].max() >= shape[1]):
        raise DifferenceInputError(f"lidar_pixel: a pixel lies outside the {shape[0]} x {shape[1]} image")
    return RangePairs(pixel, measured, expected, heights[0][1] if heights else None)


class DifferenceMetric:
    """Base class: a raw per-pixel disagreement map from one world-model frame.

    Class attributes:
        name: the registry name (`metric:` in graph.yaml) and the default calibration key.
        needs_predictions: the map is only meaningful when some `pred_valid` is 1 (calibration
            skips frames without predictions for such a metric).
        needs_lidar: the map compares the lidar (`RangePairs`, passed to `compute` as `lidar`), not
            the images.
    """

    name: ClassVar[str] = ""
    needs_predictions: ClassVar[bool] = False
    needs_lidar: ClassVar[bool] = False

    @classmethod
    def from_options(cls, options: MetricOptions) -> DifferenceMetric:
        """Build the metric; metrics that load weights override this and fail early on bad files."""
        return cls()

    @property
    def calibration_key(self) -> str:
        """Which entry of a calibration file holds this metric's scale."""
        return self.name or type(self).__name__

    def compute(self, target: np.ndarray, recon: np.ndarray, preds: np.ndarray, pred_valid: np.ndarray) -> np.ndarray:
        """Validated inputs in, (h, w) float32 raw map out."""
        raise NotImplementedError

    def notes(self, pred_valid: np.ndarray) -> dict[str, Any]:
        """Extra metadata for this frame's output message (e.g. how many predictions were used)."""
        return {}

    def side_arrays(self, shape: tuple[int, int], lidar: RangePairs | None) -> dict[str, np.ndarray]:
        """Arrays this frame's output message carries beside its map (the lidar's `above_returns`)."""
        return {}

    def __call__(
        self,
        target: np.ndarray,
        recon: np.ndarray,
        preds: np.ndarray,
        pred_valid: np.ndarray,
        lidar: RangePairs | None = None,
    ) -> np.ndarray:
        """Validate the frame arrays, then compute the map (a `needs_lidar` metric also gets `lidar`)."""
        h, w = validate_frame(target, recon, preds, pred_valid)
        if self.needs_lidar:
            if lidar is None:
                raise DifferenceInputError(
                    f"{type(self).__name__}: no lidar returns; expected the frame's arrays {', '.join(RANGE_PAIR_ARRAYS)}"
                )
            extra = {"lidar": validate_range_pairs(lidar, (h, w))}
        else:
            extra = {}
        out = np.asarray(self.compute(target, recon, preds, pred_valid, **extra), dtype=np.float32)
        if out.shape != (h, w):
            raise DifferenceInputError(f"{type(self).__name__}.compute: expected a ({h}, {w}) map, got {out.shape}")
        return out


def abs_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Δ_ABS: per pixel, mean over r, g, b of |a - b|; (h, w, 3) x2 -> (h, w) float32."""
    return np.abs(a - b).mean(axis=-1, dtype=np.float32)


class AbsDifference(DifferenceMetric):
    """Δ_ABS(x, x̂_t): mean absolute colour error per pixel."""

    name = "abs"

    def compute(self, target, recon, preds, pred_valid):
        return abs_map(target, recon)


class MseDifference(DifferenceMetric):
    """Δ_MSE(x, x̂_t): mean squared colour error per pixel."""

    name = "mse"

    def compute(self, target, recon, preds, pred_valid):
        diff = target - recon
        return (diff * diff).mean(axis=-1, dtype=np.float32)


def gaussian_kernel_1d(sigma: float, radius: int) -> np.ndarray:
    """The normalised 1-D Gaussian of scipy.ndimage.gaussian_filter1d (taps -radius..radius)."""
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


class SsimDifference(DifferenceMetric):
    """Δ_SSIM = 1 - SSIM map (Wang et al. 2004), per channel then averaged over r, g, b.

    Gaussian window of 11 taps (sigma 1.5, truncated at 3.5 sigma), population covariances,
    κ1 = (0.01 L)², κ2 = (0.03 L)² with data range L = 1; edges mirrored (`dcba|abcd`) as
    scikit-image does, so the map equals
    `1 - structural_similarity(..., gaussian_weights=True, full=True)[1].mean(-1)`.
    All five local moments of all three channels are filtered at once by one separable pass.
    """

    name = "ssim"
    sigma: ClassVar[float] = 1.5
    truncate: ClassVar[float] = 3.5
    data_range: ClassVar[float] = 1.0

    def __init__(self) -> None:
        self.radius = int(self.truncate * self.sigma + 0.5)  # 5 -> 11 taps
        self.kernel = gaussian_kernel_1d(self.sigma, self.radius)
        self.c1 = (0.01 * self.data_range) ** 2
        self.c2 = (0.03 * self.data_range) ** 2

    def _blur(self, stack: np.ndarray) -> np.ndarray:
        """Gaussian-filter every (h, w) plane of a (k, h, w) float64 stack, edges mirrored (OpenCV's
        BORDER_REFLECT, scipy's `reflect`): the same numbers as scipy's `correlate1d` along both axes,
        in less time (docs/experiments.md)."""
        stack = np.ascontiguousarray(stack)
        out = np.empty(stack.shape)
        for plane, blurred in zip(stack, out, strict=True):
            cv2.sepFilter2D(plane, cv2.CV_64F, self.kernel, self.kernel, dst=blurred, borderType=cv2.BORDER_REFLECT)
        return out

    def ssim_map(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """SSIM per pixel, averaged over channels: (h, w, 3) x2 -> (h, w) float32.

        Moments are filtered in float64: in float32, `E[x²] - E[x]²` loses the variance of smooth
        regions (sky, road) to cancellation, off by 1e-4 from the exact map.
        """
        x = a.transpose(2, 0, 1).astype(np.float64)  # (3, h, w)
        y = b.transpose(2, 0, 1).astype(np.float64)
        ux, uy, uxx, uyy, uxy = np.split(self._blur(np.concatenate([x, y, x * x, y * y, x * y])), 5)
        return self._similarity(ux, uy, uxx - ux * ux, uyy - uy * uy, uxy - ux * uy).astype(np.float32)

    def _similarity(self, ux, uy, vx, vy, vxy) -> np.ndarray:
        """SSIM from the windows' means, variances and covariance, (3, h, w) each; channel mean (h, w)."""
        num = (2 * ux * uy + self.c1) * (2 * vxy + self.c2)
        den = (ux * ux + uy * uy + self.c1) * (vx + vy + self.c2)
        return (num / den).mean(axis=0)

    def compute(self, target, recon, preds, pred_valid):
        h, w = target.shape[:2]
        if min(h, w) < 2 * self.radius + 1:
            raise DifferenceInputError(f"target: SSIM needs images of at least 11x11 pixels, got {h}x{w}")
        return 1.0 - self.ssim_map(target, recon)


class ShiftedSsimDifference(SsimDifference):
    """Δ_SSIM_shift (ours, not the paper's) = 1 - the largest SSIM between the camera's window at a
    pixel and the reconstruction's windows centred up to `shift` pixels from it, each way.

    A world model at 128 x 192 draws far structure (facade edges, poles, lane marks) a pixel or two
    off; plain SSIM scores every such edge, and at the horizon those edges outrank a small obstacle.
    Here a window the reconstruction holds nearby is not a disagreement, while an object the
    reconstruction lacks stays one. Beyond the image both are mirrored as in SSIM (so offset 0 is
    SSIM itself and the map never exceeds Δ_SSIM), and every moment of a window pair is taken over
    the same extended pixels, so each SSIM stays in [-1, 1]. The moments of each image are filtered once;
    only the cross moment is filtered again per offset, so shift 2 (25 offsets) costs well under 25
    SSIMs (`umad bench differences`; docs/benchmarks.md).
    """

    name = "ssim_shift"
    shift: ClassVar[int] = 2  # chosen on validation seed 2 and a validation stress set (docs/experiments.md)

    def ssim_map(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        r, pad = self.shift, self.radius
        h, w = a.shape[:2]
        x = np.pad(a.transpose(2, 0, 1).astype(np.float64), ((0, 0), (pad, pad), (pad, pad)), mode="symmetric")
        y = np.pad(
            b.transpose(2, 0, 1).astype(np.float64), ((0, 0), (pad + r, pad + r), (pad + r, pad + r)), mode="symmetric"
        )

        def window_means(stack: np.ndarray) -> np.ndarray:  # Gaussian window means where the window fits
            return self._blur(stack)[:, pad:-pad, pad:-pad]

        ux, uxx = np.split(window_means(np.concatenate([x, x * x])), 2)  # (3, h, w) each
        uy, uyy = np.split(window_means(np.concatenate([y, y * y])), 2)  # (3, h + 2r, w + 2r) each
        vx = uxx - ux * ux
        offsets = [(dy, dx) for dy in range(2 * r + 1) for dx in range(2 * r + 1)]
        uxy = window_means(
            np.concatenate([x * y[:, dy : dy + h + 2 * pad, dx : dx + w + 2 * pad] for dy, dx in offsets])
        )
        best = np.full((h, w), -np.inf)
        for k, (dy, dx) in enumerate(offsets):
            uy_k, uyy_k = uy[:, dy : dy + h, dx : dx + w], uyy[:, dy : dy + h, dx : dx + w]
            similarity = self._similarity(ux, uy_k, vx, uyy_k - uy_k * uy_k, uxy[3 * k : 3 * k + 3] - ux * uy_k)
            np.maximum(best, similarity, out=best)
        return best.astype(np.float32)


class TemporalDifference(DifferenceMetric):
    """Δ_TD = mean over the available past predictions i of Δ_ABS(x̂_{t|t-i}, x̂_t).

    Rule at the start of a run: only predictions with `pred_valid[i-1] == 1` count, so frame 1 uses
    one prediction, frame 2 two, ... up to n. Frame 0 has none: its map is all zeros (nothing was
    predicted, so nothing is unexpected) and its metadata says `temporal_predictions: 0`.
    """

    name = "temporal"
    needs_predictions = True

    def compute(self, target, recon, preds, pred_valid):
        valid = np.flatnonzero(pred_valid)
        if valid.size == 0:
            return np.zeros(target.shape[:2], dtype=np.float32)
        return np.abs(preds[valid] - recon[None]).mean(axis=(0, 3), dtype=np.float32)

    def notes(self, pred_valid: np.ndarray) -> dict[str, Any]:
        used = int(np.count_nonzero(pred_valid))
        notes: dict[str, Any] = {"temporal_predictions": used}
        if used == 0:
            notes["temporal_note"] = "no past prediction of this frame (run start): map is zeros"
        return notes


class LidarDifference(DifferenceMetric):
    """Δ_LIDAR (ours): how much of the range the world model expected on the ground something blocks.

    Per lidar return in the camera's view whose expected point lies on the ground (less than
    `ground_height_m` above the vehicle's origin: an obstacle on the road blocks a beam the model
    expected to reach the road; a pole or a facade beside it, which the decoded range view smooths
    away, is not that), max(0, 1 - r / r̂) with r the range measured and r̂ the range the model's
    reconstructed lidar view holds there: 0 where the return lies as far as expected or farther,
    towards 1 where an object stands well before the road the model expected. Returns expected above
    the ground count 0; a frame of a world model that sends no expected heights counts every return.
    A pixel takes the largest value of the returns in it; a pixel without a return takes the value of
    the nearest pixel with one within `fill_px` (the returns land about a pixel apart at model
    resolution), else 0 (the sky, above the lidar's beams). The light does not enter it.
    """

    name = "lidar"
    needs_lidar = True
    fill_px = 2.0
    ground_height_m = 0.5  # chosen on validation seed 2 (12 drives) among 0.3, 0.5, 1.0 m and weights 0, 0.3, 0.5
    #   for returns above it (docs/experiments.md)

    def compute(self, target, recon, preds, pred_valid, lidar: RangePairs):
        h, w = target.shape[:2]
        blocked = np.zeros((h, w), np.float32)
        if len(lidar.range) == 0:
            return blocked
        share = np.maximum(0.0, 1.0 - lidar.range / np.maximum(lidar.expected, 1e-3)).astype(np.float32)
        if lidar.expected_height is not None:
            share = np.where(lidar.expected_height < self.ground_height_m, share, 0.0).astype(np.float32)
        np.maximum.at(blocked, (lidar.pixel[:, 0], lidar.pixel[:, 1]), share)
        seen = np.zeros((h, w), bool)
        seen[lidar.pixel[:, 0], lidar.pixel[:, 1]] = True
        distance, (rows, cols) = distance_transform_edt(~seen, return_indices=True)
        return np.where(distance <= self.fill_px, blocked[rows, cols], 0.0).astype(np.float32)

    def side_arrays(self, shape: tuple[int, int], lidar: RangePairs | None) -> dict[str, np.ndarray]:
        """`above_returns`: where fusion may weigh the camera maps down (its `above_lidar_weight`)."""
        return {ABOVE_RETURNS_ARRAY: above_returns(lidar.pixel, shape).astype(np.uint8)}


def above_returns(
    pixel: np.ndarray, shape: tuple[int, int], margin_px: float = 2.0, column_reach: int = 2
) -> np.ndarray:
    """(h, w) bool: the pixels more than `margin_px` rows above the topmost lidar return of their
    column and of the `column_reach` columns either side (a column without returns counts as the
    image's bottom). There the lidar found nothing standing within its range (the sky), or its beams
    do not reach (above the top beam); an object on the road has returns on it and lies below.
    `pixel`: (n, 2) rows and columns, as `RangePairs.pixel`."""
    h, w = shape
    top = np.full(w, h, np.int64)
    np.minimum.at(top, pixel[:, 1], pixel[:, 0])
    top_near = minimum_filter1d(top, size=2 * column_reach + 1, mode="nearest")
    return np.arange(h)[:, None] < (top_near[None, :] - margin_px)
