"""SegmentMeIfYouCan component metrics on hand-made frames and against a direct transcription."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from umad_common.metrics.components import SIOU_THRESHOLDS, ComponentMetrics, component_metrics, frame_components


def blank(h=10, w=12):
    return np.zeros((h, w), np.float32), np.zeros((h, w), np.uint8)


def test_exact_hit():
    scores, labels = blank()
    labels[2:5, 2:5] = 1
    scores[2:5, 2:5] = 1.0
    siou, ppv = frame_components(scores, labels, 0.5)
    assert siou.tolist() == [1.0] and ppv.tolist() == [1.0]


def test_prediction_twice_the_object():
    scores, labels = blank()
    labels[2:4, 2:4] = 1  # 4 pixels
    scores[2:4, 2:6] = 1.0  # 8 pixels, 4 on the object
    siou, ppv = frame_components(scores, labels, 0.5)
    assert siou.tolist() == [0.5] and ppv.tolist() == [0.5]


def test_one_prediction_over_two_objects_is_not_punished_twice():
    scores, labels = blank()
    labels[1:3, 1:3] = 1  # object A: 4 px
    labels[1:3, 6:9] = 1  # object B: 6 px
    scores[1:3, 1:9] = 1.0  # one predicted component covering both plus 6 px between
    siou, ppv = frame_components(scores, labels, 0.5)
    # A: intersection 4, union = 4 + 6 background px (B's pixels are adjusted away) = 10
    assert siou.tolist() == [pytest.approx(0.4), pytest.approx(6 / 12)]
    assert ppv.tolist() == [pytest.approx(10 / 16)]


def test_missed_object_and_false_alarm():
    scores, labels = blank()
    labels[0:2, 0:2] = 1
    scores[7:9, 7:9] = 1.0
    siou, ppv = frame_components(scores, labels, 0.5)
    assert siou.tolist() == [0.0] and ppv.tolist() == [0.0]
    m = ComponentMetrics(0.5)
    m.update(scores, labels)
    result = m.compute()
    assert result["mean_F1"] == 0.0 and result["n_truth_components"] == 1 and result["n_predicted_components"] == 1


def test_ignore_region_drops_predictions_and_pixels():
    scores, labels = blank()
    labels[2:4, 2:4] = 1
    labels[:, 8:] = 255
    scores[2:4, 2:4] = 1.0
    scores[0:5, 9:12] = 1.0  # only inside the ignore region
    siou, ppv = frame_components(scores, labels, 0.5)
    assert siou.tolist() == [1.0] and ppv.tolist() == [1.0]


def test_diagonal_pixels_are_one_component():
    scores, labels = blank()
    labels[1, 1] = labels[2, 2] = 1
    scores[1, 1] = scores[2, 2] = 1.0
    siou, ppv = frame_components(scores, labels, 0.5)
    assert siou.size == 1 and ppv.size == 1


def test_size_filters():
    scores, labels = blank()
    labels[0:4, 0:4] = 1
    labels[8, 8] = 1  # one-pixel object: becomes ignored with min_truth_size=2
    scores[0:4, 0:4] = 1.0
    scores[6, 0] = 1.0  # one-pixel false alarm: removed with min_predicted_size=2
    siou, ppv = frame_components(scores, labels, 0.5)
    assert siou.size == 2 and ppv.size == 2
    siou, ppv = frame_components(scores, labels, 0.5, min_predicted_size=2, min_truth_size=2)
    assert siou.tolist() == [1.0] and ppv.tolist() == [1.0]


def test_f1_counts_over_thresholds():
    scores, labels = blank(20, 20)
    labels[0:2, 0:2] = 1
    scores[0:2, 0:4] = 1.0  # sIoU 0.5, PPV 0.5
    m = ComponentMetrics(0.5)
    m.update(scores, labels)
    result = m.compute()
    for t in SIOU_THRESHOLDS:
        expected = 1.0 if t <= 0.5 else 0.0  # TP and no FP, or FN and FP
        assert result["F1"][f"{t:.2f}"] == expected
    assert result["mean_F1"] == pytest.approx(6 / 11)


def test_no_components_is_nan():
    scores, labels = blank()
    result = component_metrics([(scores, labels)], threshold=0.5)
    assert math.isnan(result["mean_F1"]) and math.isnan(result["sIoU"])


def test_best_f1_threshold_is_chosen_when_none_given():
    scores, labels = blank()
    labels[2:5, 2:5] = 1
    scores[2:5, 2:5] = 0.8
    scores[7:9, 7:9] = 0.6
    result = component_metrics([(scores, labels)])
    # best pixel F1 keeps only 0.8-scored pixels; strict ">" as the benchmark excludes them: threshold == 0.8
    assert result["threshold"] == pytest.approx(0.8, abs=1e-3)


def transcription(scores, labels, threshold):
    """The benchmark's definitions written out with set operations, one component at a time."""
    structure = np.ones((3, 3))
    truth, _ = ndimage.label(labels == 1, structure)
    pred, _ = ndimage.label((scores.astype(np.float16) > threshold) & (labels != 255), structure)
    roi = labels != 255
    truth, pred = truth[roi], pred[roi]
    siou = []
    for i in np.unique(truth[truth > 0]):
        touching = np.unique(pred[(truth == i) & (pred > 0)])
        in_pred = np.isin(pred, touching)
        inter = np.sum((truth == i) & in_pred)
        other_objects = (truth > 0) & (truth != i)
        union = np.sum(((truth == i) | in_pred) & ~other_objects)
        siou.append(inter / union)
    ppv = [np.sum((pred == j) & (truth > 0)) / np.sum(pred == j) for j in np.unique(pred[pred > 0])]
    return np.array(siou), np.array(ppv)


@pytest.mark.parametrize("seed", range(8))
def test_random_frames_match_transcription(seed):
    rng = np.random.default_rng(seed)
    labels = (ndimage.uniform_filter(rng.random((40, 50)), 5) > 0.58).astype(np.uint8)
    labels[rng.random((40, 50)) < 0.03] = 255
    scores = ndimage.uniform_filter(rng.random((40, 50)), 3) + 0.2 * (labels == 1)
    siou, ppv = frame_components(scores, labels, 0.6)
    ref_siou, ref_ppv = transcription(scores, labels, 0.6)
    np.testing.assert_allclose(siou, ref_siou)
    np.testing.assert_allclose(ppv, ref_ppv)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="equal shape"):
        frame_components(np.zeros((3, 3)), np.zeros((3, 4), np.uint8), 0.5)
    with pytest.raises(ValueError, match="finite"):
        ComponentMetrics(float("nan"))
