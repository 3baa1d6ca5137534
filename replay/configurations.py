"""The ablation table's configurations: its weight rows, in order, and the mask settings they are
scored with, and how tables name both.

A configuration (`Config`) is one cell of the table: a weight row (which difference maps are fused,
at what weights, on which normalisation) and a mask setting (a segmenter's masks with one
refinement, or no mask). The rows are the paper's 15 in its order, then ours (`weight_rows`); the
shipped configuration's weights join as one more row where no row has them (`with_shipped_row`).
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

PAPER_METRICS = ("abs", "mse", "ssim", "perceptual", "temporal")
REFINE_MODES = ("mean", "max", "single", "single_keep_raw", "mean_pixel")  # the last two are ours, not the paper's
PAPER_TRIPLES = (  # the paper's 1/3 rows, none with TD, in its order
    ("mse", "ssim", "perceptual"),
    ("abs", "ssim", "perceptual"),
    ("abs", "mse", "perceptual"),
    ("abs", "mse", "ssim"),
)
EXTRA_GROUPS = (  # rows of ours after the paper's: TD in a triple
    ("ssim", "perceptual", "temporal"),
    ("abs", "ssim", "temporal"),
)
STAND_INS = {"ssim": "ssim_shift"}  # a paper map -> the map of ours scored again in its place
LIDAR = "lidar"  # the lidar difference (ours): scored alone and added to every min-max group
LIDAR_SHARE = Fraction(1, 3)  # the lidar map's weight in a group it is added to (the group's own weights
#   scale by 1 - LIDAR_SHARE); chosen on validation seed 2 among 1/6, 1/3 and 1/2 (docs/experiments.md)


@dataclass(frozen=True)
class WeightRow:
    """One fusion weight row of the ablation table."""

    weights: dict[str, Fraction]  # metric -> weight, metrics in PAPER_METRICS order
    extra: bool = False  # True: a row of ours, not in the paper's table
    normalization: str = "minmax"  # of the maps it fuses: minmax (as logged, the paper's) or robust (ours)
    every_mode: bool = False  # True: every refinement scored whatever the maps (the shipped row added last)
    above_lidar_weight: float = 1.0  # the camera maps' factor above the lidar's returns (fusion's, ours); 1: none
    lidar_camera_exponent: float = 0.0  # the lidar map scaled by the camera maps' agreement (fusion's, ours); 0: none

    @property
    def modes(self) -> tuple[str, ...]:
        """The refinements scored for this row: all of them on the paper's maps, `mean` and `mean_pixel` on ours."""
        paper_maps = self.normalization == "minmax" and set(self.weights) <= set(PAPER_METRICS)
        return REFINE_MODES if paper_maps or self.every_mode else ("mean", "mean_pixel")

    def scores(self, mode: str) -> bool:
        """Whether this row is scored with refinement `mode` (`none`: no mask)."""
        return mode == "none" or mode in self.modes


def paper_weight_rows() -> list[WeightRow]:
    """The 15 weight rows of the UMAD ablation in the paper's order: each metric alone; the four
    triples at 1/3 (MSE+SSIM+PD, ABS+SSIM+PD, ABS+MSE+PD, ABS+MSE+SSIM); the five quadruples at 1/4
    leaving out ABS, MSE, SSIM, PD, TD in turn; all five at 1/5."""
    quadruples = [tuple(m for m in PAPER_METRICS if m != left_out) for left_out in PAPER_METRICS]
    groups = [(m,) for m in PAPER_METRICS] + list(PAPER_TRIPLES) + quadruples + [PAPER_METRICS]
    return [WeightRow({m: Fraction(1, len(group)) for m in group}) for group in groups]


def weight_rows() -> list[WeightRow]:
    """Every row the sweep computes: the paper's 15, then ours: EXTRA_GROUPS at equal weights, every
    one of those groups that holds a map in STAND_INS again with the stand-in, then all of those
    groups again on robust-normalised maps, then the lidar rows (`lidar_rows`) of the min-max groups."""
    extras = [WeightRow({m: Fraction(1, len(group)) for m in group}, extra=True) for group in EXTRA_GROUPS]
    groups = paper_weight_rows() + extras
    stand_ins = [
        WeightRow({STAND_INS.get(m, m): w for m, w in row.weights.items()}, extra=True)
        for row in groups
        if set(row.weights) & set(STAND_INS)
    ]
    minmax_rows = groups + stand_ins
    robust_rows = [WeightRow(row.weights, extra=True, normalization="robust") for row in minmax_rows]
    return minmax_rows + robust_rows + lidar_rows(minmax_rows)


def lidar_rows(groups: list[WeightRow]) -> list[WeightRow]:
    """The lidar map alone, then each of `groups` with the lidar added at LIDAR_SHARE (ours)."""
    rows = [WeightRow({LIDAR: Fraction(1)}, extra=True)]
    for row in groups:
        weights = {m: w * (1 - LIDAR_SHARE) for m, w in row.weights.items()}
        rows.append(WeightRow({**weights, LIDAR: LIDAR_SHARE}, extra=True))
    return rows


METRIC_ORDER = (*PAPER_METRICS, *STAND_INS.values(), LIDAR)  # how a row lists its metrics


def shipped_weights(shipped: dict | None) -> dict[str, Fraction] | None:
    """The shipped configuration's fusion weights as fractions of their sum, in METRIC_ORDER (others
    after), or None without a shipped configuration."""
    if not shipped or not shipped["weights"]:
        return None
    total = sum(shipped["weights"].values())
    order = sorted(
        shipped["weights"], key=lambda m: (METRIC_ORDER.index(m) if m in METRIC_ORDER else len(METRIC_ORDER), m)
    )
    return {m: Fraction(shipped["weights"][m] / total).limit_denominator(1000) for m in order}


def shipped_row_index(rows: list[WeightRow], shipped: dict | None) -> int | None:
    """The first min-max row with the shipped weights that is scored with its refinement, or None."""
    weights = shipped_weights(shipped)
    if weights is None:
        return None
    return next(
        (
            i
            for i, row in enumerate(rows)
            if row.normalization == "minmax"
            and row.weights == weights
            and row.above_lidar_weight == shipped.get("above_lidar_weight", 1.0)
            and row.lidar_camera_exponent == shipped.get("lidar_camera_exponent", 0.0)
            and row.scores(shipped["mode"])
        ),
        None,
    )


def with_shipped_row(rows: list[WeightRow], shipped: dict | None) -> list[WeightRow]:
    """`rows`, and the shipped weights as one more row (every refinement scored) where none has them."""
    if shipped_weights(shipped) is None or shipped_row_index(rows, shipped) is not None:
        return rows
    row = WeightRow(
        shipped_weights(shipped),
        extra=True,
        every_mode=True,
        above_lidar_weight=shipped.get("above_lidar_weight", 1.0),
        lidar_camera_exponent=shipped.get("lidar_camera_exponent", 0.0),
    )
    return [*rows, row]


@dataclass(frozen=True)
class Config:
    """One table cell's configuration: a weight row and a mask setting."""

    row: int  # index into the weight rows
    segmenter: str | None  # segmenter op id; None = no mask
    mode: str  # one of REFINE_MODES, or none (no mask)


def weights_label(weights: dict[str, Fraction]) -> str:
    """Short name of a weight row: `ssim`, `abs+ssim+perceptual (1/3)`, `all - temporal (1/4)`, `all (1/5)`."""
    names = list(weights)
    if len(names) == 1:
        return names[0]
    if LIDAR in weights:
        rest = {m: w / (1 - weights[LIDAR]) for m, w in weights.items() if m != LIDAR}
        return f"{weights_label(rest)} + lidar {weights[LIDAR]}"
    share = (
        f"({Fraction(1, len(names))})"
        if len(set(weights.values())) == 1
        else "(" + ", ".join(map(str, weights.values())) + ")"
    )
    if set(names) == set(PAPER_METRICS):
        return f"all {share}"
    missing = [m for m in PAPER_METRICS if m not in names]
    if len(missing) == 1 and set(names) <= set(PAPER_METRICS):
        return f"all - {missing[0]} {share}"
    return "+".join(names) + f" {share}"


def masks_name(segmenters: dict[str, str], op: str) -> str:
    """How tables name a segmenter op's masks (`segmenters`: op -> method): its method, or
    `method (op)` when several ops of the run share that method (two configurations of one
    segmenter compared side by side)."""
    method = segmenters.get(op, op)
    shared = sum(m == method for m in segmenters.values()) > 1
    return f"{method} ({op})" if shared else method
