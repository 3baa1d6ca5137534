"""The report's diagnosis on hand-made frames whose answers are known: where the top 1 % of a map's
pixels lie, and the anomaly's frame-relative score against frames since it became visible."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score

from umad_common.metrics.diagnosis import (
    Diagnosis,
    ErrorLocation,
    ScoreSinceVisible,
    frame_relative_scores,
    top_pixels,
)

SKY, ROAD, ANIMAL = 11, 1, 30


def sky_over_road(h=10, w=10) -> np.ndarray:
    semantic = np.full((h, w), ROAD, np.uint8)
    semantic[: h // 2] = SKY
    return semantic


def test_top_pixels_takes_the_ceiling_of_the_fraction_and_breaks_ties_by_position():
    scores = np.array([0.2, 0.9, 0.9, 0.1, 0.5])
    assert top_pixels(scores, 0.01).tolist() == [1]  # at least one pixel; of the tied two, the first
    assert top_pixels(scores, 0.5).tolist() == [1, 2, 4]  # ceil(2.5) = 3
    assert top_pixels(scores, 1.0).tolist() == [0, 1, 2, 3, 4]
    flat = np.random.default_rng(1).random(1000).round(2)  # many ties
    expected = np.sort(np.argsort(-flat, kind="stable")[:10])
    assert top_pixels(flat, 0.01).tolist() == expected.tolist()


def test_error_location_counts_each_frames_top_percent_by_class():
    semantic = sky_over_road()
    loc = ErrorLocation()  # 1 % of 100 pixels: one pixel per frame
    on_sky = np.zeros((10, 10))
    on_sky[1, 1] = 1.0
    on_road = np.zeros((10, 10))
    on_road[8, 3] = 1.0
    loc.update(on_sky, semantic)
    assert loc.compute() == {SKY: 1.0}
    loc.update(on_road, semantic)
    loc.update(on_road, semantic)
    assert loc.compute() == pytest.approx({ROAD: 2 / 3, SKY: 1 / 3})
    assert list(loc.compute()) == [ROAD, SKY]  # largest share first
    assert loc.frames == 3


def test_error_location_leaves_out_ignored_pixels_and_pools_a_larger_fraction():
    semantic = sky_over_road()
    semantic[5, :2] = ANIMAL
    scores = np.zeros((10, 10))
    scores[0, :] = 0.9  # ten sky pixels, the highest but one row...
    scores[0, 0] = 5.0  # ...one of them ignored
    scores[5, :2] = 0.95  # the object
    valid = np.ones((10, 10), bool)
    valid[0, 0] = False
    loc = ErrorLocation(fraction=0.1)  # 10 of the 99 valid pixels (ceil 9.9)
    loc.update(scores, semantic, valid)
    assert loc.compute() == pytest.approx({SKY: 0.8, ANIMAL: 0.2})


def test_error_location_refuses_mismatched_shapes_and_bad_fractions():
    with pytest.raises(ValueError, match=r"expected one \(h, w\) shape"):
        ErrorLocation().update(np.zeros((4, 4)), np.zeros((4, 5), np.uint8))
    with pytest.raises(ValueError, match="fraction"):
        ErrorLocation(fraction=0.0)
    assert ErrorLocation().compute() == {}


def test_frame_relative_scores_by_hand_and_rank_equals_the_frames_auroc():
    scores = np.array([[0.9, 0.9, 0.1, 0.5, 0.9, 1.0, 0.3]])
    labels = np.array([[1, 1, 0, 0, 0, 0, 255]])
    out = frame_relative_scores(scores, labels)
    assert out["rank"] == pytest.approx((2 + 0.5) / 4)  # above 0.1 and 0.5, tied with 0.9, below 1.0
    assert out["ratio"] == pytest.approx(0.9 / np.mean([0.1, 0.5, 0.9, 1.0]))
    assert out["ratio_p99"] == pytest.approx(0.9 / (0.9 + 0.97 * 0.1))  # linear 99th percentile
    rng = np.random.default_rng(0)
    scores, labels = rng.random((20, 30)), (rng.random((20, 30)) < 0.1).astype(np.uint8)
    scores = np.round(scores, 1)  # ties
    labels[0, :3] = 255
    keep = labels != 255
    expected = roc_auc_score(labels[keep], scores[keep])
    assert frame_relative_scores(scores, labels)["rank"] == pytest.approx(expected)
    assert frame_relative_scores(scores, np.zeros_like(labels)) is None


def object_frames(first_visible=5, n=30, fade_from=15):
    """An object appearing at seq 5; its score above every normal pixel until seq 14, then equal
    to the normal pixels (rank 0.5); no anomaly pixel at seq 20."""
    for seq in range(n):
        labels = np.zeros((4, 4), np.uint8)
        scores = np.full((4, 4), 0.2)
        if seq >= first_visible and seq != 20:
            labels[1:3, 1:3] = 1
            scores[1:3, 1:3] = 0.8 if seq < fade_from else 0.2
        yield seq, scores, labels


def test_score_since_visible_bins_frames_from_the_first_visible_one():
    tracker = ScoreSinceVisible(bin_frames=10)
    for seq, scores, labels in object_frames():
        tracker.update("a", seq, scores, labels)
    assert tracker.first_visible == {"a": 5}
    bins = tracker.compute()["a"]
    assert [(b["from"], b["to"], b["frames"]) for b in bins] == [(0, 9, 10), (10, 19, 9), (20, 29, 5)]
    assert bins[0]["rank"] == 1.0 and bins[0]["ratio"] == pytest.approx(4.0)  # seq 5..14: 0.8 vs 0.2
    assert bins[1]["rank"] == pytest.approx(0.5) and bins[1]["ratio"] == pytest.approx(1.0)  # seq 15..24 but 20
    assert bins[2]["rank"] == pytest.approx(0.5)
    assert tracker.compute()["all"] == bins


def test_score_since_visible_pools_scenarios_and_refuses_frames_out_of_order():
    tracker = ScoreSinceVisible(bin_frames=100)
    for seq, scores, labels in object_frames():
        tracker.update("a", seq, scores, labels)
        tracker.update("b", seq, scores, np.zeros_like(labels))  # never visible: not counted
    assert set(tracker.compute()) == {"a", "all"} and tracker.first_visible == {"a": 5}
    with pytest.raises(ValueError, match="ascending seq"):
        tracker.update("a", 3, np.zeros((4, 4)), np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match="bin_frames"):
        ScoreSinceVisible(bin_frames=0)


def test_diagnosis_per_scenario_overall_and_without_labels():
    semantic = sky_over_road(8, 8)
    diagnosis = Diagnosis(fraction=0.01, bin_frames=5)
    for run, hot in (("a", (0, 0)), ("b", (6, 6))):
        for seq in range(3):
            labels = np.zeros((8, 8), np.uint8)
            labels[4, 4] = 1
            fused = np.zeros((8, 8), np.float32)
            fused[hot] = 1.0
            fused[4, 4] = 0.5
            half = fused[::2, ::2]  # a map at half size: labels and classes are resized to it
            diagnosis.update(run, seq, labels, semantic, {"abs": half, "fused": fused}, {"fused": fused})
    diagnosis.update("c", 0, np.zeros((8, 8), np.uint8), None, {"fused": np.ones((8, 8))}, {})
    diagnosis.update("d", 0, np.zeros((8, 8), np.uint8), np.zeros((8, 8), np.uint8), {"fused": np.ones((8, 8))}, {})
    out = diagnosis.compute()
    assert out["location"]["a"]["fused"] == {SKY: 1.0} and out["location"]["b"]["fused"] == {ROAD: 1.0}
    assert out["location"]["overall"]["fused"] == {ROAD: 0.5, SKY: 0.5}
    assert out["location"]["a"]["abs"] == {SKY: 1.0}
    assert "c" not in out["location"] and "d" not in out["location"]  # no semantic labels
    assert out["first_visible"] == {"a": 0, "b": 0}
    curve = out["since_visible"]["fused"]["a"]
    assert curve[0]["frames"] == 3 and curve[0]["rank"] == pytest.approx(62 / 63)  # above all normal pixels but one
