"""Fusion and mask refinement: arithmetic on hand-made maps and masks whose answer is known, plus
the fusion and mask_refiner operators over a short stream (metrics joining and leaving, weight
changes applying from the next frame)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from umad_common.dataflow import Frame
from umad_common.dataflow.api.messages import Message
from umad_common.refine import fuse, mask_scores, refine, resize_nearest, scale_by_camera_agreement
from umad_operators.fusion import Fusion
from umad_operators.mask_refiner import MaskRefiner

FUSED = np.array(
    [
        [0.0, 0.2, 0.4, 0.6],
        [0.8, 1.0, 0.1, 0.3],
    ],
    dtype=np.float32,
)


def masks_of(*boxes: list[list[int]]) -> np.ndarray:
    return np.array(boxes, dtype=bool)


LEFT = [[1, 1, 0, 0], [1, 1, 0, 0]]  # mean 0.5, max 1.0
RIGHT = [[0, 0, 1, 1], [0, 0, 1, 1]]  # mean 0.35, max 0.6
MIDDLE = [[0, 1, 1, 0], [0, 1, 1, 0]]  # mean 0.425, max 1.0
CORNER = [[0, 0, 0, 1], [0, 0, 0, 0]]  # mean 0.6, max 0.6


def test_mean_writes_each_masks_mean_to_its_pixels():
    out = refine(FUSED, masks_of(LEFT, RIGHT), mode="mean")
    np.testing.assert_allclose(out, [[0.5, 0.5, 0.35, 0.35], [0.5, 0.5, 0.35, 0.35]], rtol=1e-6)
    assert out.dtype == np.float32


def test_max_writes_each_masks_max_to_its_pixels():
    out = refine(FUSED, masks_of(LEFT, RIGHT), mode="max")
    np.testing.assert_allclose(out, [[1.0, 1.0, 0.6, 0.6], [1.0, 1.0, 0.6, 0.6]], rtol=1e-6)


def test_single_gives_every_pixel_outside_the_best_mask_the_frames_lowest_score():
    """The paper's single mask: LEFT (mean 0.5) wins; everything else, covered or not, gets min 0.0."""
    shifted = FUSED + 0.25  # frame minimum 0.25, so "lowest score" is not confused with zero
    for uncovered in ("keep", "zero"):
        out = refine(shifted, masks_of(RIGHT, LEFT, MIDDLE), mode="single", uncovered=uncovered)
        np.testing.assert_allclose(out, [[0.75, 0.75, 0.25, 0.25], [0.75, 0.75, 0.25, 0.25]], rtol=1e-6)
    corner_wins = refine(shifted, masks_of(CORNER, RIGHT), mode="single")  # CORNER mean 0.85 beats RIGHT 0.6
    np.testing.assert_allclose(corner_wins, [[0.25, 0.25, 0.25, 0.85], [0.25, 0.25, 0.25, 0.25]], rtol=1e-6)


def test_single_keep_raw_keeps_the_best_mask_and_the_uncovered_rule_elsewhere():
    out = refine(FUSED, masks_of(RIGHT, LEFT, MIDDLE), mode="single_keep_raw", uncovered="zero")
    np.testing.assert_allclose(out, [[0.5, 0.5, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]], rtol=1e-6)
    kept = refine(FUSED, masks_of(RIGHT, LEFT), mode="single_keep_raw", uncovered="keep")
    np.testing.assert_allclose(kept, [[0.5, 0.5, 0.4, 0.6], [0.5, 0.5, 0.1, 0.3]], rtol=1e-6)


def test_mean_pixel_keeps_a_share_of_each_covered_pixels_own_score():
    """LEFT's mean 0.5 with a quarter of each pixel's own score; the uncovered rule holds elsewhere."""
    out = refine(FUSED, masks_of(LEFT), mode="mean_pixel", uncovered="zero", pixel_share=0.25)
    expected = [[0.375, 0.425, 0.0, 0.0], [0.575, 0.625, 0.0, 0.0]]
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(
        refine(FUSED, masks_of(LEFT, RIGHT), mode="mean_pixel", pixel_share=0.0),
        refine(FUSED, masks_of(LEFT, RIGHT), mode="mean"),
    )
    np.testing.assert_allclose(refine(FUSED, masks_of(LEFT), mode="mean_pixel", pixel_share=1.0), FUSED, rtol=1e-6)


def test_mean_pixel_keeps_a_small_object_inside_a_large_mask_above_its_surroundings():
    """A 2-pixel object in a 400-pixel segment: `mean` gives every pixel the segment's score, so the
    object ties with its background; `mean_pixel` ranks it first within the segment."""
    fused = np.full((20, 20), 0.1, dtype=np.float32)
    fused[5, 5:7] = 0.9
    segment = np.ones((1, 20, 20), dtype=bool)
    mean = refine(fused, segment, mode="mean")
    assert mean[5, 5] == mean[0, 0]
    mixed = refine(fused, segment, mode="mean_pixel")
    assert mixed[5, 5] > mixed[0, 0] and mixed[5, 5] == mixed[5, 6]


def test_none_returns_the_fused_map():
    out = refine(FUSED, masks_of(LEFT), mode="none", uncovered="zero")
    np.testing.assert_array_equal(out, FUSED)
    assert out is not FUSED


def test_overlap_highest_score_wins_in_either_order():
    expected = [[0.5, 0.5, 0.425, 0.6], [0.5, 0.5, 0.425, 0.0]]  # LEFT beats MIDDLE, CORNER beats MIDDLE
    for order in ([LEFT, MIDDLE, CORNER], [CORNER, MIDDLE, LEFT], [MIDDLE, CORNER, LEFT]):
        out = refine(FUSED, masks_of(*order), mode="mean", uncovered="zero")
        np.testing.assert_allclose(out, expected, rtol=1e-6)


def test_uncovered_pixels_keep_or_zero():
    keep = refine(FUSED, masks_of(CORNER), mode="mean", uncovered="keep")
    expected_keep = FUSED.copy()
    expected_keep[0, 3] = 0.6
    np.testing.assert_allclose(keep, expected_keep, rtol=1e-6)
    zero = refine(FUSED, masks_of(CORNER), mode="max", uncovered="zero")
    np.testing.assert_allclose(zero, [[0, 0, 0, 0.6], [0, 0, 0, 0]], rtol=1e-6)


def test_no_masks_and_empty_masks_leave_every_pixel_uncovered():
    no_masks = np.zeros((0, 2, 4), dtype=bool)
    np.testing.assert_array_equal(refine(FUSED, no_masks, uncovered="keep"), FUSED)
    np.testing.assert_array_equal(
        refine(FUSED, no_masks, mode="single_keep_raw", uncovered="zero"), np.zeros_like(FUSED)
    )
    empty = np.zeros((1, 2, 4), dtype=bool)
    for mode in ("mean", "mean_pixel", "max", "single_keep_raw"):
        np.testing.assert_array_equal(refine(FUSED, empty, mode=mode, uncovered="keep"), FUSED)
    for masks in (no_masks, empty):  # no mask survives: every pixel gets the frame's lowest score
        np.testing.assert_array_equal(refine(FUSED + 0.25, masks, mode="single"), np.full_like(FUSED, 0.25))


def test_mask_scores_match_a_per_mask_loop_on_random_overlapping_masks():
    rng = np.random.default_rng(3)
    fused = rng.random((17, 23)).astype(np.float32)
    masks = rng.random((40, 17, 23)) < 0.2
    masks[5] = False
    means, maxes = mask_scores(fused, masks, "mean"), mask_scores(fused, masks, "max")
    for k in range(len(masks)):
        if masks[k].any():
            assert means[k] == pytest.approx(fused[masks[k]].astype(np.float64).mean(), rel=1e-12)
            assert maxes[k] == fused[masks[k]].max()
        else:
            assert means[k] == -np.inf and maxes[k] == -np.inf
    out = refine(fused, masks, mode="mean", uncovered="zero")
    per_pixel_best = np.where(masks, means[:, None, None], 0.0).max(axis=0)
    np.testing.assert_allclose(out, per_pixel_best, rtol=1e-6)


def test_refine_rejects_bad_arguments():
    with pytest.raises(ValueError, match="mode"):
        refine(FUSED, masks_of(LEFT), mode="median")
    with pytest.raises(ValueError, match="uncovered"):
        refine(FUSED, masks_of(LEFT), uncovered="nan")
    with pytest.raises(ValueError, match="pixel_share"):
        refine(FUSED, masks_of(LEFT), mode="mean_pixel", pixel_share=1.5)
    with pytest.raises(ValueError, match=r"expected \(K, 2, 4\)"):
        refine(FUSED, np.zeros((1, 3, 4), dtype=bool))


def test_fuse_is_the_weighted_mean_of_the_maps_present():
    a, b = np.full((2, 3), 0.2, np.float32), np.full((2, 3), 0.8, np.float32)
    out = fuse({"abs": a, "ssim": b}, {"abs": 0.25, "ssim": 0.75, "td": 1.0})  # td absent: ignored
    np.testing.assert_allclose(out, 0.65, rtol=1e-6)
    assert out.dtype == np.float32 and out.shape == (2, 3)
    unweighted = fuse({"abs": a, "mnad": b}, {"abs": 0.5})  # mnad has no weight: not fused
    np.testing.assert_allclose(unweighted, 0.2, rtol=1e-6)
    np.testing.assert_array_equal(fuse({"abs": a}, {"abs": 0.0}), np.zeros((2, 3), np.float32))


def test_fuse_resizes_to_the_largest_map_and_ignores_arrival_order():
    big = np.linspace(0, 1, 8 * 12, dtype=np.float32).reshape(8, 12)
    small = np.full((4, 6), 0.5, np.float32)
    one = fuse({"abs": big, "mnad": small}, {"abs": 0.5, "mnad": 0.5})
    other = fuse({"mnad": small, "abs": big}, {"mnad": 0.5, "abs": 0.5})
    assert one.shape == (8, 12)
    np.testing.assert_array_equal(one, other)
    np.testing.assert_allclose(one, (big + 0.5) / 2, rtol=1e-6)


def test_resize_nearest_matches_opencv_exact_nearest():
    cv2 = pytest.importorskip("cv2")
    labels = np.arange(7 * 11, dtype=np.int32).reshape(7, 11)
    for shape in ((3, 5), (14, 22), (7, 4), (10, 11)):
        expected = cv2.resize(labels, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST_EXACT)
        np.testing.assert_array_equal(resize_nearest(labels, shape), expected)


def map_msg(seq: int, metric: str | None, value: float, shape=(2, 3)) -> Message:
    meta = {"metric": metric} if metric else {}
    return Message("drive", seq, meta=meta, arrays={"map": np.full(shape, value, np.float32)})


def fusion_frame(seq: int, maps: dict[str, Message], partial: bool = False) -> Frame:
    return Frame("drive", seq, 0, many={"maps": maps}, partial=partial)


def test_fusion_stream_with_a_metric_joining_and_leaving():
    op = Fusion({"weights": {"abs": 0.5, "ssim": 0.5}})
    first = op.process(fusion_frame(0, {"diff_abs": map_msg(0, "abs", 0.2)}))["fused"]
    np.testing.assert_allclose(first.arrays["map"], 0.2)
    assert first.meta == {"metrics": ["abs"], "weights": {"abs": 0.5}, "ignored": [], "partial": False}
    both = {"diff_abs": map_msg(1, "abs", 0.2), "diff_ssim": map_msg(1, "ssim", 0.6)}
    joined = op.process(fusion_frame(1, both))["fused"]
    np.testing.assert_allclose(joined.arrays["map"], 0.4, rtol=1e-6)
    assert joined.meta["metrics"] == ["abs", "ssim"] and joined.meta["weights"] == {"abs": 0.5, "ssim": 0.5}
    left = op.process(fusion_frame(2, {"diff_ssim": map_msg(2, "ssim", 0.6)}, partial=True))["fused"]
    np.testing.assert_allclose(left.arrays["map"], 0.6, rtol=1e-6)
    assert left.meta["metrics"] == ["ssim"] and left.meta["partial"] is True


def test_fusion_weight_change_applies_from_the_next_frame():
    op = Fusion({"weights": {"abs": 0.5, "ssim": 0.5}})
    maps = {"diff_abs": map_msg(0, "abs", 0.0), "diff_ssim": map_msg(0, "ssim", 1.0)}
    before = op.process(fusion_frame(0, maps))["fused"]
    np.testing.assert_allclose(before.arrays["map"], 0.5, rtol=1e-6)
    op.update_params(Fusion.validate_params({"weights": {"abs": 0.5, "ssim": 0.0}}))
    after = op.process(fusion_frame(1, maps))["fused"]
    np.testing.assert_allclose(after.arrays["map"], 0.0)
    assert after.meta["metrics"] == ["abs"] and after.meta["ignored"] == ["ssim"]
    assert after.meta["weights"] == {"abs": 0.5}


def test_fusion_metric_falls_back_to_producer_id_and_defaults_cover_five_metrics():
    op = Fusion()
    assert op.params.weights == {"abs": 0.2, "mse": 0.2, "ssim": 0.2, "perceptual": 0.2, "temporal": 0.2}
    out = op.process(fusion_frame(0, {"temporal": map_msg(0, None, 0.3), "mnad": map_msg(0, None, 0.9)}))["fused"]
    np.testing.assert_allclose(out.arrays["map"], 0.3, rtol=1e-6)
    assert out.meta["metrics"] == ["temporal"] and out.meta["ignored"] == ["mnad"]


def test_fusion_rejects_bad_weights_and_inputs():
    with pytest.raises(ValidationError, match="ssim"):
        Fusion({"weights": {"ssim": 1.5}})
    with pytest.raises(ValidationError):
        Fusion({"weight": {"ssim": 0.5}})
    with pytest.raises(ValidationError, match="above_lidar_weight"):
        Fusion({"above_lidar_weight": 1.5})
    bad_mask = map_msg(0, "lidar", 0.5)
    bad_mask.arrays["above_returns"] = np.ones((2, 2, 2), np.uint8)
    with pytest.raises(ValueError, match=r"the mask has shape \(2, 2, 2\); expected \(h, w\)"):
        Fusion({"above_lidar_weight": 0.5}).process(
            fusion_frame(0, {"diff_lidar": bad_mask, "diff_abs": map_msg(0, "abs", 0.1)})
        )
    op = Fusion()
    with pytest.raises(ValueError, match="two producers report metric 'abs'"):
        op.process(fusion_frame(0, {"a1": map_msg(0, "abs", 0.1), "a2": map_msg(0, "abs", 0.2)}))
    with pytest.raises(ValueError, match="no difference maps"):
        op.process(fusion_frame(0, {}))


def test_mask_refiner_operator_resizes_masks_nearest():
    fused = np.zeros((4, 8), np.float32)
    fused[:2, :4] = 1.0
    masks = np.zeros((2, 2, 4), dtype=bool)
    masks[0, 0, :2] = True  # the top-left quarter at full size
    masks[1, 1, :] = True  # the bottom half
    frame = Frame(
        "drive",
        0,
        0,
        inputs={
            "fused": Message("drive", 0, arrays={"map": fused}),
            "masks": Message("drive", 0, arrays={"masks": masks}),
        },
    )
    out = MaskRefiner({"mode": "mean", "uncovered": "zero"}).process(frame)["refined"]
    expected = np.zeros((4, 8), np.float32)
    expected[:2, :4] = 1.0
    np.testing.assert_array_equal(out.arrays["map"], expected)
    assert out.meta == {"mode": "mean", "uncovered": "zero", "masks": 2, "partial": False}
    fused[0, 0] = 0.0  # the top-left mask's mean becomes 7/8
    mixed = MaskRefiner({"mode": "mean_pixel", "pixel_share": 0.5}).process(frame)["refined"]
    expected[:2, :4] = 0.5 * 0.875 + 0.5
    expected[0, 0] = 0.5 * 0.875
    np.testing.assert_allclose(mixed.arrays["map"], expected, rtol=1e-6)
    assert mixed.meta["pixel_share"] == 0.5
    with pytest.raises(ValidationError):
        MaskRefiner({"mode": "median"})
    with pytest.raises(ValidationError, match="pixel_share"):
        MaskRefiner({"mode": "mean_pixel", "pixel_share": 2})


def test_the_lidar_map_counts_where_the_camera_maps_disagree_too():
    rng = np.random.default_rng(3)
    abs_map, ssim_map, lidar = (rng.random((6, 8)).astype(np.float32) for _ in range(3))
    mse_map = np.ones((6, 8), np.float32)
    maps = {"abs": abs_map, "ssim": ssim_map, "mse": mse_map, "lidar": lidar}
    weights = {"abs": 0.2, "ssim": 0.6, "mse": 0.0, "lidar": 0.5}
    out = scale_by_camera_agreement(maps, "lidar", weights, 0.5)
    camera = (0.2 * abs_map + 0.6 * ssim_map) / 0.8  # mse has weight 0: no part of the agreement
    scaled = lidar * np.sqrt(camera / camera.max())
    np.testing.assert_allclose(out["lidar"], (scaled - scaled.min()) / (scaled.max() - scaled.min()), atol=1e-6)
    assert all(out[m] is maps[m] for m in ("abs", "ssim", "mse"))

    equal_lidar = {"abs": np.array([[0.1, 0.9]], np.float32), "lidar": np.array([[0.8, 0.8]], np.float32)}
    agreed = scale_by_camera_agreement(equal_lidar, "lidar", {"abs": 1.0, "lidar": 1.0}, 1.0)["lidar"]
    assert agreed[0, 0] < agreed[0, 1]  # the same lidar evidence counts less where the camera map agrees

    for unchanged in (
        scale_by_camera_agreement(maps, "lidar", weights, 0.0),  # exponent 0: the paper's fusion
        scale_by_camera_agreement({"lidar": lidar}, "lidar", weights, 0.5),  # no camera map
        scale_by_camera_agreement({**maps, "abs": 0 * abs_map, "ssim": 0 * ssim_map}, "lidar", weights, 0.5),
    ):
        assert unchanged["lidar"] is lidar
    with pytest.raises(ValueError, match="exponent is -1"):
        scale_by_camera_agreement(maps, "lidar", weights, -1.0)
    with pytest.raises(ValidationError, match="lidar_camera_exponent"):
        Fusion({"lidar_camera_exponent": -0.5})
