"""PixelMetrics against scikit-learn on float16-quantised scores."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sklearn.metrics import average_precision_score, roc_auc_score, roc_curve

from umad_common.metrics.pixel import PixelMetrics


def reference(scores: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    """scikit-learn on the float16 scores of the non-ignored pixels."""
    keep = labels != 255
    s = scores[keep].astype(np.float16).astype(np.float64)
    s = np.clip(s, -1e9, 1e9)  # scikit-learn refuses inf; order is kept (float16 max is 65504)
    y = labels[keep].astype(int)
    fpr, tpr, _ = roc_curve(y, s, drop_intermediate=False)
    return {
        "AP": average_precision_score(y, s),
        "AUROC": roc_auc_score(y, s),
        "FPR95": float(fpr[np.searchsorted(tpr, 0.95, side="left")]),
    }


def assert_matches(result: dict, ref: dict) -> None:
    for key in ("AP", "AUROC", "FPR95"):
        assert result[key] == pytest.approx(ref[key], rel=1e-12, abs=1e-12), key


@pytest.mark.parametrize("seed", range(5))
def test_random_scores_match_sklearn(seed):
    rng = np.random.default_rng(seed)
    labels = (rng.random(20_000) < 0.1).astype(np.uint8)
    scores = rng.normal(size=labels.size).astype(np.float32) + 1.5 * labels
    m = PixelMetrics()
    m.update(scores, labels)
    assert_matches(m.compute(), reference(scores, labels))


def test_heavy_ties_and_negative_scores():
    rng = np.random.default_rng(1)
    labels = (rng.random(10_000) < 0.3).astype(np.uint8)
    scores = np.round(rng.normal(size=labels.size) + labels, 1) - 0.5  # few distinct values, both signs
    scores[:50] = -0.0
    scores[50:100] = 0.0
    scores[100:110] = np.inf
    scores[110:120] = -np.inf
    m = PixelMetrics()
    m.update(scores, labels)
    assert_matches(m.compute(), reference(scores, labels))


def test_negative_zero_equals_positive_zero():
    labels = np.array([1, 0, 1, 0], dtype=np.uint8)
    a, b = PixelMetrics(), PixelMetrics()
    a.update(np.array([0.0, -0.0, -0.0, 0.0]), labels)
    b.update(np.zeros(4), labels)
    assert a.compute() == b.compute()
    assert a.compute()["AP"] == 0.5


def test_float16_quantisation_merges_close_scores():
    """Scores equal after float16 rounding are ties, as SegmentMeIfYouCan stores them."""
    labels = np.array([1, 0], dtype=np.uint8)
    m = PixelMetrics()
    m.update(np.array([0.5000001, 0.5], dtype=np.float32), labels)
    assert m.compute()["AP"] == 0.5
    assert m.compute()["AUROC"] == 0.5


def test_constant_map():
    labels = np.array([0, 0, 1, 0, 1, 0], dtype=np.uint8)
    m = PixelMetrics()
    m.update(np.full(6, 0.3), labels)
    result = m.compute()
    assert result["AP"] == pytest.approx(2 / 6)
    assert result["AUROC"] == 0.5
    assert result["FPR95"] == 1.0
    assert_matches(result, reference(np.full(6, 0.3), labels))


def test_perfect_separation():
    m = PixelMetrics()
    m.update(np.array([0.9, 0.8, 0.1, 0.2]), np.array([1, 1, 0, 0]))
    result = m.compute()
    assert (result["AP"], result["AUROC"], result["FPR95"]) == (1.0, 1.0, 0.0)


def test_all_normal_frames_give_nan_then_pool():
    """AP/AUROC/FPR95 are undefined without anomaly pixels (NaN); pooling later frames fixes that."""
    m = PixelMetrics()
    m.update(np.random.default_rng(0).random((8, 8)), np.zeros((8, 8), np.uint8))
    result = m.compute()
    assert math.isnan(result["AP"]) and math.isnan(result["AUROC"]) and math.isnan(result["FPR95"])
    assert result["n_normal"] == 64 and result["n_anomaly"] == 0
    m.update(np.array([[2.0]]), np.array([[1]], np.uint8))
    assert m.compute()["AP"] == 1.0


def test_all_anomaly_frames():
    m = PixelMetrics()
    m.update(np.array([0.1, 0.5]), np.array([1, 1]))
    result = m.compute()
    assert result["AP"] == 1.0
    assert math.isnan(result["AUROC"]) and math.isnan(result["FPR95"])


def test_ignore_pixels_are_excluded():
    rng = np.random.default_rng(2)
    labels = rng.choice(np.array([0, 1, 255], np.uint8), size=(64, 64), p=[0.6, 0.2, 0.2])
    scores = rng.random((64, 64)).astype(np.float32) + 0.3 * (labels == 1)
    m = PixelMetrics()
    m.update(scores, labels)
    result = m.compute()
    assert result["n_ignored"] == int((labels == 255).sum())
    assert result["n_anomaly"] + result["n_normal"] + result["n_ignored"] == labels.size
    assert_matches(result, reference(scores.ravel(), labels.ravel()))
    scores_changed = scores.copy()
    scores_changed[labels == 255] = 100.0  # whatever ignored pixels score, nothing changes
    other = PixelMetrics()
    other.update(scores_changed, labels)
    assert other.compute() == result


def test_multiple_updates_and_merge_equal_one_pool():
    rng = np.random.default_rng(3)
    frames = [
        (rng.random((16, 24)) + 0.5 * (lab := (rng.random((16, 24)) < 0.1)), lab.astype(np.uint8)) for _ in range(6)
    ]
    streamed, first, second = PixelMetrics(), PixelMetrics(), PixelMetrics()
    for i, (s, y) in enumerate(frames):
        streamed.update(s, y)
        (first if i < 3 else second).update(s, y)
    pooled_scores = np.concatenate([s.ravel() for s, _ in frames])
    pooled_labels = np.concatenate([y.ravel() for _, y in frames])
    assert_matches(streamed.compute(), reference(pooled_scores, pooled_labels))
    assert first.merge(second).compute() == streamed.compute()


def test_curves_are_consistent_with_sklearn():
    rng = np.random.default_rng(4)
    labels = (rng.random(5000) < 0.2).astype(np.uint8)
    scores = rng.random(5000) + 0.4 * labels
    m = PixelMetrics()
    m.update(scores, labels)
    roc = m.roc_curve()
    ref_fpr, ref_tpr, _ = roc_curve(labels, scores.astype(np.float16).astype(np.float64), drop_intermediate=False)
    np.testing.assert_allclose(roc["fpr"], ref_fpr)
    np.testing.assert_allclose(roc["tpr"], ref_tpr)
    pr = m.pr_curve()
    assert pr["recall"][0] == 0.0 and pr["recall"][-1] == 1.0
    assert np.all(np.diff(pr["recall"]) >= 0)
    threshold = m.best_f1_threshold()
    predicted = scores.astype(np.float16) >= threshold
    f1 = 2 * (predicted & (labels == 1)).sum() / (predicted.sum() + labels.sum())
    for t in np.unique(scores.astype(np.float16))[::50]:
        other = scores.astype(np.float16) >= t
        assert 2 * (other & (labels == 1)).sum() / (other.sum() + labels.sum()) <= f1 + 1e-12


def test_integer_and_bool_inputs():
    m = PixelMetrics()
    m.update(np.array([3, 1, 2], dtype=np.int64), np.array([True, False, False]))
    assert m.compute()["AP"] == 1.0


def test_bad_inputs_are_refused_with_clear_errors():
    m = PixelMetrics()
    with pytest.raises(ValueError, match="NaN"):
        m.update(np.array([0.1, np.nan]), np.array([0, 1]))
    with pytest.raises(ValueError, match="same shape"):
        m.update(np.zeros(3), np.zeros(4, np.uint8))
    with pytest.raises(ValueError, match="0 \\(normal\\), 1 \\(anomaly\\) or 255"):
        m.update(np.zeros(3), np.array([0, 2, 1], np.uint8))
    with pytest.raises(ValueError, match="0, 1 or 255"):
        m.update(np.zeros(2), np.array([0, -1]))
    with pytest.raises(ValueError, match="integers"):
        m.update(np.zeros(2), np.array([0.0, 1.0]))
    assert m.n_normal == 0 and m.n_anomaly == 0  # nothing half-counted


def test_counts_per_score_equal_the_map_that_holds_those_pixels():
    rng = np.random.default_rng(3)
    scores = np.array([0.25, 0.7, 0.25, 1e-5], np.float32)  # a repeated score: its counts add up
    normal, anomaly, ignored = np.array([3, 0, 2, 5]), np.array([1, 4, 0, 2]), 6
    labels = np.concatenate([np.repeat([0] * 4, normal), np.repeat([1] * 4, anomaly), np.full(ignored, 255)])
    values = np.concatenate([np.repeat(scores, normal), np.repeat(scores, anomaly), rng.random(ignored)])
    via_counts, via_pixels = PixelMetrics(), PixelMetrics()
    via_counts.update_counts(scores, normal, anomaly, ignored)
    via_pixels.update(values, labels)
    assert np.array_equal(via_counts.hist, via_pixels.hist) and via_counts.n_ignored == via_pixels.n_ignored == 6
    with pytest.raises(ValueError, match="one of each per score"):
        via_counts.update_counts(scores, normal[:3], anomaly)
    with pytest.raises(ValueError, match="NaN"):
        via_counts.update_counts(np.array([np.nan]), [1], [0])


def test_float32_scores_take_numpys_float16_patterns_bit_for_bit():
    """The sweep's fast float32 -> float16 conversion equals numpy's cast: every rounding tie of the
    normal range and of the subnormals, the overflow to infinity at 65520, signed zeros, and a
    million values over 19 decades."""
    from umad_common.metrics.pixel import _float16_patterns

    half_bits = np.arange(1 << 15, dtype=np.uint16)
    halves = half_bits.view(np.float16).astype(np.float32)
    finite = halves[np.isfinite(halves)]
    nudged = np.concatenate([np.nextafter(finite, np.inf), np.nextafter(finite, -np.inf)])
    ties = (finite[:-1].astype(np.float64) + finite[1:]) / 2  # exactly halfway: rounds to the even pattern
    rng = np.random.default_rng(3)
    spread = rng.standard_normal(10**6) * 10.0 ** rng.integers(-12, 7, 10**6)
    edges = [0.0, -0.0, np.inf, -np.inf, 65504.0, 65519.996, 65520.0, 1e-8, 2.0**-25, 3 * 2.0**-26, 1e30]
    values = np.concatenate([finite, nudged, ties, spread, edges]).astype(np.float32)
    values = np.concatenate([values, -values])
    with np.errstate(over="ignore"):  # numpy warns where it casts past 65504 to infinity
        expected = values.astype(np.float16).view(np.uint16)
    assert np.array_equal(_float16_patterns(values), expected)
    assert _float16_patterns(np.zeros(0, np.float32)).size == 0
