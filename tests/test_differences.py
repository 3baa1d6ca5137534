"""Difference metrics, normalisation, VGG16/feature-net loading and the difference operator.

Each formula is checked against an independent reference: explicit numpy loops for ABS, MSE,
temporal and the perceptual sum, scikit-image for SSIM, numpy for the normalisations.
"""

from __future__ import annotations

import json
import sys

import cv2
import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from umad_common.dataflow import Context, Frame
from umad_common.dataflow.api.messages import Message
from umad_common.differences import (
    AbsDifference,
    CalibrationError,
    CalibrationFitter,
    DifferenceInputError,
    MseDifference,
    ShiftedSsimDifference,
    SsimDifference,
    TemporalDifference,
    UnknownMetricError,
    build_metric,
    calibrated,
    load_calibration,
    minmax,
    robust,
)
from umad_common.differences.perceptual import PerceptualDifference
from umad_common.models.feature_net import FeatureNet, load_feature_net, save_feature_net
from umad_common.models.vgg16 import load_vgg16_features
from umad_common.models.weights import WeightsError

torch.set_num_threads(1)


def random_frame(h: int = 24, w: int = 32, n: int = 3, seed: int = 0):
    rng = np.random.default_rng(seed)
    target = rng.random((h, w, 3), dtype=np.float32)
    recon = np.clip(target + 0.2 * rng.standard_normal((h, w, 3)), 0, 1).astype(np.float32)
    preds = rng.random((n, h, w, 3), dtype=np.float32)
    return target, recon, preds, np.ones(n, dtype=np.uint8)


def synthetic_frame(h: int = 48, w: int = 64):
    """A road-like picture and a blurred, shifted reconstruction with a missing square 'object'."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    target = np.stack([yy / h, xx / w, 0.5 + 0.5 * np.sin(xx / 3)], axis=-1).astype(np.float32)
    target[h // 3 : h // 2, w // 3 : w // 2] = (1.0, 0.1, 0.1)
    recon = cv2.GaussianBlur(np.stack([yy / h, xx / w, 0.5 + 0.5 * np.sin(xx / 3)], -1), (5, 5), 1.0).astype(np.float32)
    preds = np.stack([np.roll(recon, 1, axis=1), np.roll(recon, 2, axis=1)])
    return target, recon, preds, np.array([1, 0], dtype=np.uint8)


FRAMES = [random_frame(), random_frame(31, 45, 2, seed=1), synthetic_frame()]


@pytest.mark.parametrize("frame", FRAMES)
def test_abs_and_mse_match_pixel_loops(frame):
    target, recon, preds, valid = frame
    h, w = target.shape[:2]
    ref_abs = np.zeros((h, w))
    ref_mse = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            d = [float(target[y, x, c]) - float(recon[y, x, c]) for c in range(3)]
            ref_abs[y, x] = sum(abs(v) for v in d) / 3
            ref_mse[y, x] = sum(v * v for v in d) / 3
    got_abs = AbsDifference()(target, recon, preds, valid)
    got_mse = MseDifference()(target, recon, preds, valid)
    assert got_abs.dtype == np.float32 and got_abs.shape == (h, w)
    assert got_mse.dtype == np.float32 and got_mse.shape == (h, w)
    np.testing.assert_allclose(got_abs, ref_abs, atol=1e-6)
    np.testing.assert_allclose(got_mse, ref_mse, atol=1e-6)


@pytest.mark.parametrize("frame", [*FRAMES, random_frame(128, 192, 1, seed=2)])
def test_ssim_matches_scikit_image_full_map(frame):
    target, recon, preds, valid = frame
    _, full = structural_similarity(
        target.astype(np.float64),
        recon.astype(np.float64),
        full=True,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1,
        channel_axis=-1,
    )
    got = SsimDifference()(target, recon, preds, valid)
    assert got.dtype == np.float32 and got.shape == target.shape[:2]
    np.testing.assert_allclose(got, 1.0 - full.mean(axis=-1), atol=1e-4)


def test_ssim_of_identical_images_is_zero_and_tiny_images_are_refused():
    target, _, preds, valid = random_frame()
    np.testing.assert_allclose(SsimDifference()(target, target, preds, valid), 0.0, atol=1e-5)
    small = np.zeros((8, 30, 3), np.float32)
    with pytest.raises(DifferenceInputError, match="at least 11x11"):
        SsimDifference()(small, small, np.zeros((0, 8, 30, 3), np.float32), np.zeros(0, np.uint8))


@pytest.mark.parametrize("frame", FRAMES)
def test_shifted_ssim_is_the_best_ssim_over_shifted_reconstructions_away_from_the_edges(frame):
    target, recon, preds, valid = frame
    h, w = target.shape[:2]
    r = ShiftedSsimDifference.shift
    padded = np.pad(recon, ((r, r), (r, r), (0, 0)), mode="symmetric")
    shifted = [padded[dy : dy + h, dx : dx + w] for dy in range(2 * r + 1) for dx in range(2 * r + 1)]
    reference = np.min([SsimDifference()(target, np.ascontiguousarray(s), preds, valid) for s in shifted], axis=0)
    got = ShiftedSsimDifference()(target, recon, preds, valid)
    assert got.dtype == np.float32 and got.shape == (h, w)
    inner = np.s_[r + 5 : h - r - 5, r + 5 : w - r - 5]  # the 11-tap window reads no repeated edge
    np.testing.assert_allclose(got[inner], reference[inner], atol=1e-5)
    assert got.min() >= -1e-6  # edges too: every window pair's moments are over the same pixels
    assert (got <= SsimDifference()(target, recon, preds, valid) + 1e-6).all()  # offset 0 is SSIM itself


def test_shifted_ssim_forgives_a_reconstruction_drawn_a_pixel_off_but_not_a_missing_object():
    target, recon, preds, valid = synthetic_frame()
    drawn_off = np.roll(target, (1, -2), axis=(0, 1))
    drawn_off[16:24, 21:32] = recon[16:24, 21:32]  # the square 'object' (rows 16-24, cols 21-32) is not drawn
    inner = np.s_[8:-8, 8:-8]
    plain = SsimDifference()(target, drawn_off, preds, valid)[inner]
    shifted = ShiftedSsimDifference()(target, drawn_off, preds, valid)[inner]
    on_object = np.zeros(target.shape[:2], bool)
    on_object[16:24, 21:32] = True
    on_object = on_object[inner]
    assert shifted[~on_object].mean() < 0.2 * plain[~on_object].mean()
    contrast = {
        name: m[on_object].mean() / m[~on_object].mean() for name, m in (("plain", plain), ("shifted", shifted))
    }
    assert contrast["shifted"] > 3 * contrast["plain"]  # 21x against 4.6x


def test_temporal_uses_only_valid_predictions():
    target, recon, preds, _ = random_frame(12, 14, 3)
    valid = np.array([1, 0, 1], dtype=np.uint8)
    ref = np.zeros((12, 14))
    for i in (0, 2):
        for y in range(12):
            for x in range(14):
                ref[y, x] += sum(abs(float(preds[i, y, x, c]) - float(recon[y, x, c])) for c in range(3)) / 3 / 2
    metric = TemporalDifference()
    np.testing.assert_allclose(metric(target, recon, preds, valid), ref, atol=1e-6)
    assert metric.notes(valid) == {"temporal_predictions": 2}


def test_temporal_at_run_start_is_zeros_and_says_so():
    target, recon, preds, _ = random_frame(12, 14, 3)
    metric = TemporalDifference()
    start = np.zeros(3, dtype=np.uint8)
    out = metric(target, recon, preds, start)
    assert out.dtype == np.float32 and out.shape == (12, 14) and not out.any()
    assert metric.notes(start)["temporal_predictions"] == 0
    assert "run start" in metric.notes(start)["temporal_note"]
    no_slots = metric(target, recon, preds[:0], start[:0])
    assert not no_slots.any()


@pytest.mark.parametrize(
    ("position", "bad", "pattern"),
    [
        (
            0,
            np.zeros((24, 32, 3), np.float64),
            r"target: expected float32 array of shape \(h, w, 3\), got float64 \(24, 32, 3\)",
        ),
        (0, np.zeros((24, 32), np.float32), r"target: expected .*got float32 \(24, 32\)"),
        (
            1,
            np.zeros((24, 31, 3), np.float32),
            r"recon: expected float32 array of shape \(24, 32, 3\).*got float32 \(24, 31, 3\)",
        ),
        (2, np.zeros((3, 24, 32), np.float32), r"preds: expected float32 array of shape \(n, 24, 32, 3\), got float32"),
        (3, np.ones(3, np.int64), r"pred_valid: expected uint8 array of shape \(3,\).*got int64 \(3,\)"),
        (3, np.ones(2, np.uint8), r"pred_valid: expected uint8 array of shape \(3,\).*got uint8 \(2,\)"),
        (1, [[0.0]], r"recon: expected .*got list"),
    ],
)
def test_wrong_inputs_name_the_array(position, bad, pattern):
    args = list(random_frame())
    args[position] = bad
    for metric in (AbsDifference(), SsimDifference(), TemporalDifference()):
        with pytest.raises(DifferenceInputError, match=pattern):
            metric(*args)


class HandMadeExtractor(torch.nn.Module):
    """Two known feature levels: the image itself and its 2x2 average pool (for the Δ_PD formula)."""

    def forward(self, x):
        return [x, torch.nn.functional.avg_pool2d(x, 2)]


def test_perceptual_formula_matches_reference():
    target, recon, preds, valid = random_frame(16, 24)
    metric = PerceptualDifference(HandMadeExtractor(), "hand")
    got = metric(target, recon, preds, valid)
    pool = lambda im: im.reshape(8, 2, 12, 2, 3).mean(axis=(1, 3))  # noqa: E731
    level1 = np.abs(target - recon).mean(axis=-1)
    level2 = cv2.resize(np.abs(pool(target) - pool(recon)).mean(axis=-1), (24, 16), interpolation=cv2.INTER_LINEAR)
    np.testing.assert_allclose(got, level1 + level2, atol=1e-5)
    assert metric.calibration_key == "perceptual/hand"


def torchvision_vgg16_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """Random tensors under torchvision's VGG16 keys and shapes (features + a classifier key)."""
    gen = torch.Generator().manual_seed(seed)
    state, channels, index = {}, 3, 0
    for item in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"):
        if item == "M":
            index += 1
            continue
        state[f"features.{index}.weight"] = (
            torch.randn(item, channels, 3, 3, generator=gen) * (2 / (9 * channels)) ** 0.5
        )
        state[f"features.{index}.bias"] = torch.zeros(item)
        channels, index = item, index + 2
    state["classifier.6.bias"] = torch.zeros(1000)
    return state


def test_vgg16_loads_torchvision_state_dict(tmp_path):
    state = torchvision_vgg16_state()
    path = tmp_path / "vgg16.pth"
    torch.save(state, path)
    model, _ = load_vgg16_features(path)
    assert torch.equal(model.features[21].weight, state["features.21.weight"])
    levels = model(torch.rand(1, 3, 32, 48))
    assert [tuple(f.shape[1:]) for f in levels] == [(64, 32, 48), (128, 16, 24), (256, 8, 12), (512, 4, 6)]
    target, recon, preds, valid = random_frame(32, 48)
    metric = build_metric("perceptual", options=_options(vgg_weights=path))
    assert metric.calibration_key == "perceptual/vgg16"
    np.testing.assert_allclose(metric(target, target, preds, valid), 0.0, atol=0)
    out = metric(target, recon, preds, valid)
    assert out.dtype == np.float32 and out.shape == (32, 48) and out.min() > 0


def test_vgg16_shape_mismatch_names_the_layer(tmp_path):
    state = torchvision_vgg16_state()
    state["features.5.weight"] = torch.zeros(128, 32, 3, 3)
    path = tmp_path / "bad.pth"
    torch.save(state, path)
    with pytest.raises(
        WeightsError, match=r"'features.5.weight' expected shape \(128, 64, 3, 3\), got \(128, 32, 3, 3\)"
    ):
        load_vgg16_features(path)
    del state["features.5.weight"]
    torch.save(state, path)
    with pytest.raises(WeightsError, match=r"missing key 'features.5.weight'"):
        load_vgg16_features(path)
    with pytest.raises(WeightsError, match="not found"):
        load_vgg16_features(tmp_path / "absent.pth")


def _options(**kwargs):
    from umad_common.differences import MetricOptions

    return MetricOptions(**kwargs)


@pytest.fixture()
def feature_file(tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "features.safetensors"
    save_feature_net(FeatureNet(), path)
    return path


def test_feature_net_roundtrip_and_perceptual_identity(feature_file):
    loaded, _ = load_feature_net(feature_file)
    assert feature_file.with_suffix(".json").is_file()
    levels = loaded(torch.rand(2, 3, 32, 48))
    assert [tuple(f.shape) for f in levels] == [(2, 16, 32, 48), (2, 32, 16, 24), (2, 64, 8, 12), (2, 128, 4, 6)]
    target, recon, preds, valid = synthetic_frame()
    metric = build_metric("perceptual", _options(features=feature_file))
    assert metric.calibration_key == "perceptual"
    assert not metric(target, target, preds, valid).any()
    assert metric(target, recon, preds, valid).max() > 0


def test_feature_training_is_deterministic_and_small():
    from umad_common.training.train_features import FeatureTrainingConfig, train_feature_net

    frames = (np.random.default_rng(0).random((12, 128, 192, 3)) * 255).astype(np.uint8)
    cfg = FeatureTrainingConfig(epochs=1, batch_size=6)
    (a, _), (b, _) = train_feature_net(frames, cfg), train_feature_net(frames, cfg)
    for key, value in a.state_dict().items():
        assert torch.equal(value, b.state_dict()[key]), key
    assert sum(v.numel() for v in a.state_dict().values()) * 4 < 5e6


def test_minmax_and_calibrated_normalisation():
    raw = np.array([[1.0, 3.0], [2.0, 5.0]], np.float32)
    np.testing.assert_allclose(minmax(raw), [[0.0, 0.5], [0.25, 1.0]])
    assert not minmax(np.full((3, 4), 7.0, np.float32)).any()
    scores = calibrated(np.array([-1.0, 0.0, 0.5, 2.0, 1e6], np.float32), q=0.5)
    np.testing.assert_allclose(scores, [0.0, 0.0, 0.5, 0.8, 1e6 / (1e6 + 0.5)], rtol=1e-6)
    assert scores.dtype == np.float32 and scores[3] < 1.0


def test_robust_normalisation_measures_pixels_against_the_frames_bulk():
    """z / (1 + z), z = (r - median) / (P99.9 - median): 0.5 at the frame's 99.9th percentile, 0 at or
    below the median, zeros for a constant map, and unchanged by any positive affine change of r
    (so the sweep may apply it to logged min-max maps)."""
    rng = np.random.default_rng(0)
    raw = rng.gamma(2.0, 1.0, (64, 96)).astype(np.float32)
    raw[10, 10] = 1000.0  # one extreme pixel sets min-max's scale, not robust's
    median, high = np.percentile(raw, [50, 99.9])
    scores = robust(raw)
    assert scores.dtype == np.float32 and scores.shape == raw.shape
    assert scores[raw <= median].max() == 0.0 and 0.0 <= scores.min() and scores.max() < 1.0
    expected = (raw[5, 5] - median) / (high - median)
    assert scores[5, 5] == pytest.approx(max(expected, 0) / (1 + max(expected, 0)), rel=1e-5)
    assert np.median(scores[raw >= high]) >= 0.5
    np.testing.assert_allclose(robust(3.0 * raw + 7.0), scores, atol=1e-6)
    np.testing.assert_allclose(robust(minmax(raw)), scores, atol=1e-5)
    assert not robust(np.full((4, 4), 2.0, np.float32)).any()
    assert robust(np.zeros((0,), np.float32)).size == 0


def test_calibration_fit_save_load(tmp_path):
    rng = np.random.default_rng(0)
    maps = [rng.random((8, 8), dtype=np.float32) for _ in range(5)]
    fitter = CalibrationFitter()
    for m in maps:
        fitter.add("abs", m)
    calibration = fitter.fit({"world_model": "wm.safetensors"})
    assert calibration.scale("abs") == pytest.approx(np.percentile(np.concatenate([m.ravel() for m in maps]), 99.9))
    path = tmp_path / "calibration.json"
    calibration.save(path)
    loaded = load_calibration(path)
    assert loaded.scales == calibration.scales and loaded.info["world_model"] == "wm.safetensors"
    with pytest.raises(CalibrationError, match=r"no scale for metric 'ssim'; the file has \['abs'\]"):
        loaded.scale("ssim", str(path))
    path.write_text(json.dumps({"version": 1, "scales": {"abs": -1}}))
    with pytest.raises(CalibrationError, match="positive number"):
        load_calibration(path)


def frame_message(arrays) -> Frame:
    target, recon, preds, valid = arrays
    msg = Message("run", 0, arrays={"target": target, "recon": recon, "preds": preds, "pred_valid": valid})
    return Frame("run", 0, 0, inputs={"frame": msg})


@pytest.mark.parametrize("metric", ["abs", "mse", "ssim", "perceptual", "temporal"])
def test_operator_outputs_normalised_map(metric, feature_file, tmp_path):
    from umad_operators.difference import Difference

    calibration = tmp_path / "calibration.json"
    fitter = CalibrationFitter()
    fitter.add(metric, np.linspace(0.0, 1.0, 100))
    fitter.fit().save(calibration)
    ctx = Context(base_dir=tmp_path)
    frame = frame_message(synthetic_frame())
    for normalization in ("minmax", "robust", "calibrated"):
        op = Difference(
            {
                "metric": metric,
                "normalization": normalization,
                "features": feature_file.name,
                "calibration": calibration.name,
            },
            ctx,
        )
        out = op.process(frame)["map"]
        score = out.arrays["map"]
        assert score.dtype == np.float32 and score.shape == (48, 64)
        assert 0.0 <= score.min() and score.max() <= 1.0
        assert out.meta["metric"] == metric and out.meta["normalization"] == normalization
        if normalization == "robust":
            np.testing.assert_array_equal(score, robust(op.metric(*synthetic_frame())))
        if normalization == "minmax":
            assert score.max() == pytest.approx(1.0)


def test_operator_fails_early_and_loads_user_metric(tmp_path, monkeypatch):
    from pydantic import ValidationError

    from umad_operators.difference import Difference

    with pytest.raises(ValidationError):
        Difference({"metric": "abs", "colour": "red"})
    with pytest.raises(WeightsError, match="not found"):
        Difference({"metric": "perceptual", "features": str(tmp_path / "none.safetensors")})
    with pytest.raises(CalibrationError, match="calibration file not found"):
        Difference({"metric": "abs", "normalization": "calibrated", "calibration": str(tmp_path / "none.json")})
    with pytest.raises(UnknownMetricError, match="unknown metric 'nope'"):
        Difference({"metric": "nope"})
    (tmp_path / "my_metrics.py").write_text(
        "import numpy as np\nfrom umad_common.differences import DifferenceMetric\n"
        "class RedDifference(DifferenceMetric):\n"
        "    def compute(self, target, recon, preds, pred_valid):\n"
        "        return np.abs(target[..., 0] - recon[..., 0])\n"
    )
    monkeypatch.setattr(sys, "path", [str(tmp_path), *sys.path])
    op = Difference({"metric": "my_metrics:RedDifference"})
    target, recon, preds, valid = random_frame()
    score = op.process(frame_message((target, recon, preds, valid)))["map"].arrays["map"]
    np.testing.assert_allclose(score, minmax(np.abs(target[..., 0] - recon[..., 0])), atol=1e-6)


def write_generator_scenario(root, name: str, frames: int, seed: int):
    """A tiny generator-layout drive whose label files (semantic, instance, depth, anomaly) are
    undecodable: any attempt to read a label fails loudly."""
    import cv2

    rng = np.random.default_rng(seed)
    scenario = root / name
    cam = "RGB-CAM(0, 0, 1.8)(0, 0, 0)_ab12"
    lidar = "LIDAR(0, 0, 2.5)(0, 0, 0)_cd34"
    poisoned = [
        "SEMANTIC-CAM(0, 0, 1.8)(0, 0, 0)_ef56",
        "INSTANCE-CAM(0, 0, 1.8)(0, 0, 0)_ab78",
        "DEPTH_CAM(0, 0, 1.8)(0, 0, 0)_9a",
    ]
    for folder in [cam, lidar, "ACTION", "ROUTE_MAP", "ANOMALY", *poisoned]:
        (scenario / folder).mkdir(parents=True)
    for fid in range(1000, 1000 + frames):
        cv2.imwrite(str(scenario / cam / f"{cam}_{fid}.png"), (rng.random((40, 60, 3)) * 255).astype(np.uint8))
        np.save(scenario / lidar / f"{lidar}_{fid}.npy", rng.standard_normal((50, 4)).astype(np.float32))
        (scenario / "ACTION" / f"ACTION_{fid}.csv").write_text(
            "speed ; 18.0\nthrottle ; 0.5\nsteer ; 0.0\nbrake ; 0.0\n"
        )
        cv2.imwrite(str(scenario / "ROUTE_MAP" / f"ROUTE_MAP_{fid}.png"), np.zeros((192, 192), np.uint8))
        (scenario / "ANOMALY" / f"ANOMALY_{fid}.csv").write_bytes(b"\xff\xfe not a label file")
        for folder in poisoned:
            (scenario / folder / f"{folder}_{fid}.png").write_bytes(b"not a png: labels must not be read")
    return scenario


def test_calibrate_uses_heldout_normal_drives_and_never_reads_labels(tmp_path, feature_file):
    import argparse

    from umad_common.commands import calibrate
    from umad_common.datasets.anovox import AnoVoxScenario
    from umad_common.datasets.drive import DatasetError
    from umad_common.models.world_model import WorldModel, WorldModelConfig, save_world_model

    normal = tmp_path / "bench" / "normal"
    write_generator_scenario(normal, "Scenario_a", 3, seed=0)
    held = write_generator_scenario(normal, "Scenario_b", 5, seed=1)
    with pytest.raises(DatasetError):
        AnoVoxScenario(held)[0]  # the label files really are poison to a reader that opens them
    config = WorldModelConfig(
        image_height=32, image_width=48, image_channels=(8, 8), decoder_channels=(8, 8, 4), lidar_rows=16,
        lidar_width=32, lidar_channels=(8, 8), lidar_embed=8, route_size=16, route_channels=(8,), route_embed=8,
        deter_channels=4, stoch_channels=2, hidden_channels=8, transition_kernel=3, frame_step=2,
    )  # fmt: skip
    torch.manual_seed(0)
    save_world_model(WorldModel(config), tmp_path / "wm", {"heldout_drives": ["Scenario_b"]})
    out = tmp_path / "calibration.json"
    args = argparse.Namespace(
        data=tmp_path / "bench", world_model=tmp_path / "wm", features=feature_file, vgg_weights=None, metric=[],
        out=out, frames=4, horizon=2, threads=1, topics=None,
    )  # fmt: skip
    assert calibrate.run(args) == 0
    calibration = load_calibration(out)
    assert sorted(calibration.scales) == ["abs", "mse", "perceptual", "ssim", "ssim_shift", "temporal"]
    assert calibration.info["drives"] == ["Scenario_b"] and calibration.info["frames"] == 4
    assert calibration.info["stride"] == 2  # the model steps on seq 0 and 2; only seq 2 has a prediction
    assert calibration.stats["abs"]["frames"] == 4 and calibration.stats["temporal"]["frames"] == 1


def test_train_features_command_reads_only_training_rgb(tmp_path):
    import argparse

    from umad_common.commands import train_features

    normal = tmp_path / "bench" / "normal"
    write_generator_scenario(normal, "Scenario_a", 4, seed=0)
    write_generator_scenario(normal, "Scenario_b", 2, seed=1)
    out = tmp_path / "features.safetensors"
    args = argparse.Namespace(
        data=tmp_path / "bench",
        out=out,
        epochs=1,
        seed=0,
        frames=100,
        batch_size=2,
        holdout=1,
        threads=1,
        device="cpu",
        topics=None,
    )
    assert train_features.run(args) == 0
    _, record = load_feature_net(out)
    assert record["training"]["frames"] == 4 and record["training"]["heldout_drives"] == ["Scenario_b"]
    assert record["training"]["device"] == "cpu"


def test_lidar_difference_is_the_share_of_the_expected_range_that_something_blocks():
    from umad_common.differences import LidarDifference, RangePairs

    target, recon, preds, valid = random_frame(h=20, w=30)
    pairs = RangePairs(
        pixel=np.array([[5, 5], [5, 5], [15, 20], [0, 29]], np.int32),
        range=np.array([10.0, 18.0, 30.0, 25.0], np.float32),
        expected=np.array([20.0, 20.0, 20.0, 100.0], np.float32),
    )
    lidar_map = LidarDifference()(target, recon, preds, valid, lidar=pairs)
    assert lidar_map.shape == (20, 30) and lidar_map.dtype == np.float32
    assert lidar_map[5, 5] == pytest.approx(0.5)  # the larger of 1 - 10/20 and 1 - 18/20
    assert lidar_map[15, 20] == 0.0  # farther than expected: nothing in the way
    assert lidar_map[0, 29] == pytest.approx(0.75)
    assert lidar_map[7, 5] == pytest.approx(0.5) and lidar_map[5, 3] == pytest.approx(0.5)  # filled within 2 px
    assert lidar_map[8, 5] == 0.0 and lidar_map[12, 12] == 0.0  # beyond 2 px of any return
    with pytest.raises(DifferenceInputError, match="no lidar returns"):
        LidarDifference()(target, recon, preds, valid)
    # with the expected points' heights: only a beam the model expected to reach the ground counts
    on_ground = pairs._replace(expected_height=np.array([0.1, 2.5, 0.0, 0.2], np.float32))
    ground_map = LidarDifference()(target, recon, preds, valid, lidar=on_ground)
    assert ground_map[5, 5] == pytest.approx(0.5)  # 1 - 10/20, expected on the road
    assert ground_map[0, 29] == pytest.approx(0.75)
    facade = on_ground._replace(expected_height=np.array([2.5, 2.5, 0.0, 3.0], np.float32))
    assert not LidarDifference()(target, recon, preds, valid, lidar=facade).any()  # a pole, a facade: nothing
    with pytest.raises(DifferenceInputError, match="lidar_expected_height: expected float32 array of shape"):
        LidarDifference()(target, recon, preds, valid, lidar=pairs._replace(expected_height=np.zeros(3, np.float32)))
    outside = pairs._replace(pixel=np.array([[5, 5], [5, 5], [15, 20], [0, 30]], np.int32))
    with pytest.raises(DifferenceInputError, match="outside the 20 x 30 image"):
        LidarDifference()(target, recon, preds, valid, lidar=outside)


def test_lidar_operator_without_returns_says_so_once_and_fusion_leaves_its_map_out(caplog):
    from umad_operators.difference import Difference
    from umad_operators.fusion import Fusion

    target, recon, preds, valid = random_frame(h=20, w=30)
    camera_only = Message("run", 0, arrays={"target": target, "recon": recon, "preds": preds, "pred_valid": valid})
    op = Difference({"metric": "lidar"})
    with caplog.at_level("WARNING"):
        for seq in (0, 1):
            out = op.process(Frame("run", seq, seq, inputs={"frame": camera_only}))["map"]
    assert out.meta["no_data"].startswith("the world model sends no lidar returns")
    assert not out.arrays["map"].any()
    assert sum("stays out of fusion" in r.message for r in caplog.records) == 1  # once per run
    empty = {"lidar_pixel": np.zeros((0, 2), np.int32), "lidar_range": np.zeros(0, np.float32)}
    empty["lidar_expected"] = np.zeros(0, np.float32)
    no_points = Message("run", 0, arrays={**camera_only.arrays, **empty})
    assert "data without lidar" in op.process(Frame("run", 0, 0, inputs={"frame": no_points}))["map"].meta["no_data"]

    abs_map = Difference({"metric": "abs"}).process(Frame("run", 0, 0, inputs={"frame": camera_only}))["map"]
    maps = {
        "diff_abs": Message("run", 0, meta=abs_map.meta, arrays=abs_map.arrays),
        "diff_lidar": Message("run", 0, meta=out.meta, arrays=out.arrays),
    }
    fusion = Fusion({"weights": {"abs": 0.5, "lidar": 0.5}})
    fused = fusion.process(Frame("run", 0, 0, many={"maps": maps}))["fused"]
    assert fused.meta["metrics"] == ["abs"]
    np.testing.assert_array_equal(fused.arrays["map"], abs_map.arrays["map"])


def test_the_ssim_window_filter_gives_scipys_numbers():
    from scipy.ndimage import correlate1d

    stack = np.random.default_rng(5).random((4, 23, 31))
    metric = SsimDifference()
    rows = correlate1d(stack, metric.kernel, axis=1, mode="reflect")
    np.testing.assert_allclose(
        metric._blur(stack), correlate1d(rows, metric.kernel, axis=2, mode="reflect"), atol=1e-14
    )


def test_the_lidar_map_marks_the_pixels_above_its_returns_and_fusion_weighs_the_camera_down_there():
    from umad_common.differences import ABOVE_RETURNS_ARRAY, above_returns
    from umad_operators.difference import Difference
    from umad_operators.fusion import Fusion

    top = above_returns(np.array([[10, 5], [14, 5], [12, 20]], np.int32), (20, 30))
    assert top[7, 5] and not top[8, 5]  # more than 2 rows above the topmost return of column 5
    assert top[7, 3] and top[7, 7] and not top[8, 7]  # the columns within 2 of it share its top
    assert top[17, 0] and top[17, 29] and not top[18, 0]  # no return within 2 columns: as one below the image
    assert top[9, 18] and not top[10, 18] and not top[10, 22] and top[10, 23]

    target, recon, preds, valid = random_frame(h=20, w=30)
    lidar = {
        "lidar_pixel": np.array([[10, 5], [14, 5], [12, 20]], np.int32),
        "lidar_range": np.full(3, 10.0, np.float32),
        "lidar_expected": np.full(3, 10.0, np.float32),
    }
    frame_msg = Message(
        "run", 0, arrays={"target": target, "recon": recon, "preds": preds, "pred_valid": valid, **lidar}
    )
    outputs = {
        op_id: Difference({"metric": metric}).process(Frame("run", 0, 0, inputs={"frame": frame_msg}))["map"]
        for op_id, metric in (("diff_abs", "abs"), ("diff_lidar", "lidar"))
    }
    assert ABOVE_RETURNS_ARRAY not in outputs["diff_abs"].arrays
    np.testing.assert_array_equal(outputs["diff_lidar"].arrays[ABOVE_RETURNS_ARRAY], top.astype(np.uint8))
    maps = {op_id: Message("run", 0, meta=out.meta, arrays=out.arrays) for op_id, out in outputs.items()}
    camera = outputs["diff_abs"].arrays["map"]
    for weight in (1.0, 0.25):
        fusion = Fusion({"weights": {"abs": 0.5, "lidar": 0.5}, "above_lidar_weight": weight})
        fused = fusion.process(Frame("run", 0, 0, many={"maps": maps}))["fused"]
        expected = (np.where(top, weight * camera, camera) + outputs["diff_lidar"].arrays["map"]) / 2
        np.testing.assert_allclose(fused.arrays["map"], expected, rtol=1e-6)
        assert fused.meta["above_lidar_weight"] == weight
    lidar_map = np.random.default_rng(5).random((20, 30)).astype(np.float32)
    lidar_arrays = {**outputs["diff_lidar"].arrays, "map": lidar_map}
    maps["diff_lidar"] = Message("run", 0, meta=outputs["diff_lidar"].meta, arrays=lidar_arrays)
    params = {"weights": {"abs": 0.5, "lidar": 0.5}, "above_lidar_weight": 0.25, "lidar_camera_exponent": 0.5}
    fused = Fusion(params).process(Frame("run", 0, 0, many={"maps": maps}))["fused"]
    weighed = np.where(top, 0.25 * camera, camera)
    scaled = lidar_map * np.sqrt(weighed / weighed.max())  # the lidar map where the camera map disagrees too
    expected = (weighed + (scaled - scaled.min()) / (scaled.max() - scaled.min())) / 2
    np.testing.assert_allclose(fused.arrays["map"], expected, rtol=1e-5, atol=1e-6)
    assert fused.meta["lidar_camera_exponent"] == 0.5
    without_lidar = Fusion({"weights": {"abs": 0.5}, "above_lidar_weight": 0.25, "lidar_camera_exponent": 0.5})
    alone = without_lidar.process(Frame("run", 0, 0, many={"maps": {"diff_abs": maps["diff_abs"]}}))["fused"]
    np.testing.assert_array_equal(alone.arrays["map"], camera)  # nothing marks the pixels: the map as it is
    assert "above_lidar_weight" not in alone.meta and "lidar_camera_exponent" not in alone.meta
