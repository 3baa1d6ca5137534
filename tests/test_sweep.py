"""`umad sweep` on a small synthetic MCAP log written here with the mcap Writer, checked against a
direct computation with numpy + scikit-learn; a truncated log; the report files."""

from __future__ import annotations

import csv
import json
import re
from fractions import Fraction

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer
from sklearn.metrics import average_precision_score, roc_auc_score

from umad_common.cli import build_parser
from umad_common.cli import main as umad_main
from umad_common.commands.evaluate import every_and_layout
from umad_common.dataflow.api.messages import Message, encode
from umad_common.differences import robust
from umad_common.metrics.components import component_metrics
from umad_common.metrics.pixel import PixelMetrics
from umad_common.refine import refine
from umad_common.viz.headline import scored_every
from umad_common.viz.report import write_report
from umad_replay.configurations import REFINE_MODES, Config, paper_weight_rows, weight_rows, weights_label
from umad_replay.row_scoring import MaskSet, PaintedMap
from umad_replay.sweep import sweep_log

H, W, h, w = 16, 24, 8, 12  # camera / truth size, model size
METRIC_OPS = {
    "diff_abs": "abs",
    "diff_mse": "mse",
    "diff_ssim": "ssim",
    "diff_pd": "perceptual",
    "diff_td": "td",
    "diff_ssim_shift": "ssim_shift",
}


def synthetic_frames(runs=("Scenario_a", "Scenario_b"), n=6, seed=0):
    """Per frame: every message the sweep reads, plus noise it must ignore."""
    rng = np.random.default_rng(seed)
    for run in runs:
        for seq in range(n):
            anomaly = np.zeros((H, W), np.uint8)
            y, x = rng.integers(2, 10), rng.integers(2, 16)
            anomaly[y : y + 4, x : x + 6] = 1
            anomaly[0, :] = 255
            small = anomaly[1::2, 1::2]  # what nearest resize to (8, 12) picks
            maps = {op: (rng.random((h, w)) + 0.6 * (small == 1)).astype(np.float32) / 1.6 for op in METRIC_OPS}
            maps["diff_ssim"][0, 0] = 1.5  # SSIM's highest pixel is on the sky (semantic row 1)
            gt = np.stack([small == 1, small != 1])
            mnad = rng.random((H, W)).astype(np.float32) + anomaly
            # run a shows a CARLA `animal` (30), run b a `home` (29) object; sky (11) above road (1)
            semantic = np.where(anomaly == 1, 30 - runs.index(run), np.where(np.arange(H)[:, None] < H // 2, 11, 1))
            semantic = semantic.astype(np.uint8)
            tiles = np.stack([np.zeros((h, w), bool) for _ in range(4)])
            for k in range(4):
                tiles[k, :, 3 * k : 3 * k + 3] = True
            msgs = [
                (
                    "replayer",
                    "truth",
                    {"anomaly": anomaly, "instance": anomaly.astype(np.int32), "semantic": semantic},
                    {},
                ),
                ("replayer", "camera", {"rgb": rng.integers(0, 255, (H, W, 3), dtype=np.uint8)}, {}),
                (
                    "world_model",
                    "frame",
                    {
                        "target": rng.random((h, w, 3)).astype(np.float32),
                        "recon": rng.random((h, w, 3)).astype(np.float32),
                        "preds": np.zeros((2, h, w, 3), np.float32),
                        "pred_valid": np.zeros(2, np.uint8),
                    },
                    {},
                ),
                *(
                    (op, "map", {"map": maps[op]}, {"metric": METRIC_OPS[op], "normalization": "minmax"})
                    for op in METRIC_OPS
                ),
                ("seg_gt", "masks", {"masks": gt}, {"method": "gt"}),
                ("seg_felz", "masks", {"masks": tiles}, {"method": "felzenszwalb"}),
                ("mnad", "map", {"map": mnad}, {"model": "mnad"}),
                ("fusion", "fused", {"map": maps["diff_abs"]}, {"metrics": ["abs"]}),
            ]
            yield (
                run,
                seq,
                msgs,
                {
                    "anomaly": small,
                    "maps": maps,
                    "gt": gt,
                    "tiles": tiles,
                    "truth_full": anomaly,
                    "mnad": mnad,
                    "semantic": semantic,
                },
            )


def write_log(path, frames, metadata=None):
    truths = []
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.NONE, chunk_size=4096)
        writer.start(profile="umad", library="test")
        if metadata is not None:
            writer.add_metadata("umad", metadata)
        channels = {}
        viz = writer.register_channel("viz/camera", "json", 0)
        pending = []
        for run, seq, msgs, truth in frames:
            truths.append((run, seq, truth))
            pending.append([(run, seq, m) for m in msgs])
            if len(pending) == 2:  # interleave two frames, as replicas would
                a, b = pending
                mixed = [x for pair in zip(a, b, strict=True) for x in pair]
                for run_, seq_, (op, output, arrays, meta) in mixed:
                    key = f"umad/test/{op}/{output}"
                    if key not in channels:
                        channels[key] = writer.register_channel(key, "msgpack", 0)
                    payload = encode(Message(run_, seq_, seq_, op, meta, arrays))
                    writer.add_message(channels[key], seq_, payload, seq_, seq_)
                    if op == "diff_abs" and seq_ == 1:  # a retransmission: must count once
                        writer.add_message(channels[key], seq_, payload, seq_, seq_)
                writer.add_message(viz, 0, b"{}", 0, 0)
                writer.add_message(channels["umad/test/diff_mse/map"], 0, b"\x93garbage", 0, 0)
                pending = []
        writer.finish()
    return truths


GRAPH = """
name: test
operators:
  - {id: replayer, kind: replayer, params: {source: data/anomalous, every: 5}}
  - id: world_model
    kind: world_model
    inputs: {camera: replayer/camera, lidar: replayer/lidar, ego: replayer/ego, route: replayer/route}
    params: {model: models/wm.safetensors}
  - {id: diff_pd, kind: difference, inputs: {frame: world_model/frame}, params: {metric: perceptual}}
  - {id: mnad, kind: mnad, inputs: {camera: replayer/camera}, params: {weights: models/mnad.safetensors}}
  - {id: seg_gt, kind: segmenter, inputs: {frame: world_model/frame, truth: replayer/truth}, params: {method: gt}}
  - id: seg_sam
    kind: segmenter
    inputs: {frame: world_model/frame, truth: replayer/truth}
    params: {method: sam, options: {checkpoint: /weights/sam_vit_b.pth}}
"""


def write_model_records(base):
    """JSON records beside the model files GRAPH names (the weights themselves are never opened)."""
    (base / "models").mkdir(parents=True)
    (base / "models" / "wm.json").write_text(
        json.dumps({"data": "/data/normal", "training_drives": ["a", "b", "c"], "epochs": 16})
    )
    (base / "models" / "mnad.json").write_text(json.dumps({"training": {"data": "/data/mnad-normal", "epochs": 3}}))
    (base / "models" / "features.json").write_text(json.dumps({"training": {"data": "/data/features-normal"}}))


@pytest.fixture(scope="module")
def log_and_truth(tmp_path_factory):
    base = tmp_path_factory.mktemp("log")
    write_model_records(base)
    metadata = {
        "graph": GRAPH,
        "base_dir": str(base),
        "sets": json.dumps(["diff_pd.features=models/features.safetensors"]),
        "version": "test",
    }
    path = base / "run.mcap"
    truths = write_log(path, synthetic_frames(), metadata)
    return path, truths


@pytest.fixture(scope="module")
def result(log_and_truth):
    return sweep_log(log_and_truth[0], progress=False, overlay_frames=2)


def sklearn_scores(scores, labels):
    keep = labels != 255
    s = scores[keep].astype(np.float16).astype(np.float64)
    y = labels[keep]
    return average_precision_score(y, s), roc_auc_score(y, s)


def direct(truths, fused_of):
    scores = np.concatenate([fused_of(t).ravel() for _, _, t in truths])
    labels = np.concatenate([t["anomaly"].ravel() for _, _, t in truths])
    return sklearn_scores(scores, labels)


def weighted(t, weights, normalise=lambda score_map: score_map):
    metric_to_op = {("temporal" if m == "td" else m): op for op, m in METRIC_OPS.items()}
    return sum(float(wt) * normalise(t["maps"][metric_to_op[m]]) for m, wt in weights.items()) / sum(
        float(v) for v in weights.values()
    )


def refined_mean(fused, masks):
    out = fused.copy()
    for mask in masks:  # tiling masks: no overlaps
        out[mask] = fused[mask].mean()
    return out


def test_weight_rows_are_the_papers_in_its_order_then_ours():
    third, quarter, fifth = Fraction(1, 3), Fraction(1, 4), Fraction(1, 5)
    table = [  # (ABS, MSE, SSIM, PD, TD) as printed in the paper
        (1, 0, 0, 0, 0),
        (0, 1, 0, 0, 0),
        (0, 0, 1, 0, 0),
        (0, 0, 0, 1, 0),
        (0, 0, 0, 0, 1),
        (0, third, third, third, 0),
        (third, 0, third, third, 0),
        (third, third, 0, third, 0),
        (third, third, third, 0, 0),
        (0, quarter, quarter, quarter, quarter),
        (quarter, 0, quarter, quarter, quarter),
        (quarter, quarter, 0, quarter, quarter),
        (quarter, quarter, quarter, 0, quarter),
        (quarter, quarter, quarter, quarter, 0),
        (fifth,) * 5,
    ]
    metrics = ("abs", "mse", "ssim", "perceptual", "temporal")
    as_tuples = [tuple(row.weights.get(m, 0) for m in metrics) for row in paper_weight_rows()]
    assert as_tuples == table
    assert not any(row.extra for row in paper_weight_rows())
    rows = weight_rows()
    assert rows[:15] == paper_weight_rows() and all(row.extra for row in rows[15:])
    assert {tuple(row.weights) for row in rows[15:17]} == {
        ("ssim", "perceptual", "temporal"),
        ("abs", "ssim", "temporal"),
    }
    with_ssim = [row for row in rows[:17] if "ssim" in row.weights]
    assert len(with_ssim) == 11 and all(row.extra for row in rows[17:28])
    assert [list(row.weights.items()) for row in rows[17:28]] == [
        [("ssim_shift" if m == "ssim" else m, w) for m, w in row.weights.items()] for row in with_ssim
    ]
    assert all(row.normalization == "minmax" for row in rows[:28])
    assert [(row.weights, row.normalization) for row in rows[28:56]] == [(row.weights, "robust") for row in rows[:28]]
    assert rows[56].weights == {"lidar": 1} and len(rows) == 57 + 28  # the lidar alone, then with each min-max group
    for group, with_lidar in zip(rows[:28], rows[57:], strict=True):
        assert with_lidar.weights == {**{m: w * Fraction(2, 3) for m, w in group.weights.items()}, "lidar": third}
        assert with_lidar.normalization == "minmax" and sum(with_lidar.weights.values()) == 1
    assert weights_label(rows[57 + 14].weights) == "all (1/5) + lidar 1/3"
    assert [row.modes for row in (rows[0], rows[16], rows[17], rows[28], rows[56], rows[57])] == [
        REFINE_MODES,
        REFINE_MODES,
        ("mean", "mean_pixel"),
        ("mean", "mean_pixel"),
        ("mean", "mean_pixel"),
        ("mean", "mean_pixel"),
    ]


def single_mask(fused, mask):
    """The paper's single mask by hand: the winning mask's mean, the frame's lowest score elsewhere."""
    out = np.full_like(fused, fused.min())
    out[mask] = fused[mask].mean()
    return out


def test_rows_and_settings(result):
    assert result.stats.segmenters == {"seg_gt": "gt", "seg_felz": "felzenszwalb"}
    assert [s.label for s in result.paper_settings()] == [
        "gt mean",
        "felzenszwalb mean",
        "felzenszwalb max",
        "no mask",
        "felzenszwalb single",
    ]
    assert [s.label for s in result.headline_settings()][5:] == ["felzenszwalb mean_pixel"]
    assert len(result.metrics) == 17 * 11 + (11 + 28) * 5  # ours: no mask, 2 refinements
    assert result.skipped_rows == list(range(56, 85))  # the lidar rows: this log has no lidar map
    assert result.stats.frames == 12 and result.stats.duplicates == 2 and result.stats.bad == 6
    assert result.stats.truncated is None
    assert set(result.frames.values()) == {12}


def test_two_segmenters_of_one_method_are_named_by_their_ops():
    from umad_replay.configurations import masks_name

    segmenters = {"seg_gt": "gt", "segment_unsup": "geometry", "segment_nosnap": "geometry"}
    assert masks_name(segmenters, "seg_gt") == "gt"
    assert masks_name(segmenters, "segment_unsup") == "geometry (segment_unsup)"
    assert masks_name(segmenters, "segment_nosnap") == "geometry (segment_nosnap)"
    assert masks_name({"seg": "geometry"}, "seg") == "geometry"


@pytest.mark.parametrize("seed", range(3))
def test_undrawn_mask_maps_count_the_pixels_the_drawn_maps_hold(seed):
    rng = np.random.default_rng(seed)
    fused = rng.random((24, 36)).astype(np.float32)
    fused[:4, :4] = 0.5
    labels = rng.choice(np.array([0, 1, 255], np.uint8), size=(24, 36), p=[0.8, 0.15, 0.05])
    regions = rng.integers(0, 7, (24, 36))  # a partition: masks that do not overlap
    tiling = np.stack([regions == k for k in range(8)])  # mask 7 is empty
    tiling[2, :3, :] = False  # pixels no mask covers
    overlapping = rng.random((5, 24, 36)) < 0.3
    with_inf = fused.copy()
    with_inf[regions == 3] = -np.inf  # a mask whose mean is -inf: not painted
    for masks, undrawn_expected in ((tiling, True), (overlapping, False)):
        mask_set = MaskSet(masks, labels)
        for score_map in (fused, with_inf):
            with np.errstate(invalid="ignore"):  # refine's product: 0 x -inf outside the -inf mask
                undrawn = mask_set.refine_all(score_map, undrawn=True)
                drawn = mask_set.refine_all(score_map)
            for mode in REFINE_MODES:
                via_counts, via_pixels = PixelMetrics(), PixelMetrics()
                if isinstance(undrawn[mode], PaintedMap):
                    undrawn[mode].count_into(via_counts)
                else:
                    via_counts.update(undrawn[mode], labels)
                via_pixels.update(drawn[mode], labels)
                assert np.array_equal(via_counts.hist, via_pixels.hist), mode
                assert via_counts.n_ignored == via_pixels.n_ignored
            assert isinstance(undrawn["single"], PaintedMap) == undrawn_expected
            assert isinstance(undrawn["mean"], PaintedMap) == (undrawn_expected and score_map is fused)


def test_the_sources_scored_frames_and_the_sweeps_combine_as_their_least_common_multiple():
    assert scored_every({"every": 2, "score_every": 2, "world_model_every": 1, "sweep_every": 2}) == 2
    assert scored_every({"every": 6, "score_every": 2, "world_model_every": 3, "sweep_every": 5}) == 30
    assert scored_every({"every": 2, "sweep_every": 2}) == 4  # a report from before score_every was kept


@pytest.mark.parametrize("row", [0, 4, 5, 14])
def test_numbers_equal_direct_computation(result, log_and_truth, row):
    truths = log_and_truth[1]
    weights = paper_weight_rows()[row].weights
    got = result.metrics[Config(row, None, "none")].compute()
    ap, auroc = direct(truths, lambda t: weighted(t, weights))
    assert got["AP"] == pytest.approx(ap, abs=1e-12) and got["AUROC"] == pytest.approx(auroc, abs=1e-12)
    got = result.metrics[Config(row, "seg_felz", "mean")].compute()
    ap, auroc = direct(truths, lambda t: refined_mean(weighted(t, weights), t["tiles"]))
    assert got["AP"] == pytest.approx(ap, abs=1e-12) and got["AUROC"] == pytest.approx(auroc, abs=1e-12)
    got = result.metrics[Config(row, "seg_gt", "single_keep_raw")].compute()
    ap, _ = direct(truths, lambda t: refined_mean(weighted(t, weights), t["gt"][[0]]))  # the anomaly mask wins
    assert got["AP"] == pytest.approx(ap, abs=1e-12)
    got = result.metrics[Config(row, "seg_gt", "single")].compute()
    ap, _ = direct(truths, lambda t: single_mask(weighted(t, weights), t["gt"][0]))
    assert got["AP"] == pytest.approx(ap, abs=1e-12)


@pytest.mark.parametrize("row", [17, 27])
def test_stand_in_rows_fuse_the_shift_tolerant_ssim_in_the_place_of_ssim(result, log_and_truth, row):
    truths = log_and_truth[1]
    weights = weight_rows()[row].weights
    assert "ssim_shift" in weights and "ssim" not in weights
    assert Config(row, "seg_felz", "max") not in result.metrics
    got = result.metrics[Config(row, None, "none")].compute()
    ap, auroc = direct(truths, lambda t: weighted(t, weights))
    assert got["AP"] == pytest.approx(ap, abs=1e-12) and got["AUROC"] == pytest.approx(auroc, abs=1e-12)
    got = result.metrics[Config(row, "seg_felz", "mean")].compute()
    ap, _ = direct(truths, lambda t: refined_mean(weighted(t, weights), t["tiles"]))
    assert got["AP"] == pytest.approx(ap, abs=1e-12)


@pytest.mark.parametrize("row", [0, 14, 16, 17])
def test_robust_rows_fuse_robust_normalised_maps(result, log_and_truth, row):
    """Row 28 + i is row i on robust-normalised maps (docs/design.md), scored without masks and with
    `mean` refinement only, labelled as ours."""
    truths = log_and_truth[1]
    robust_row = 28 + row
    rows = weight_rows()
    assert rows[robust_row].weights == rows[row].weights and rows[robust_row].extra
    assert result.row_label(robust_row) == f"{result.row_label(row)}, robust"
    assert Config(robust_row, "seg_felz", "max") not in result.metrics
    weights = rows[row].weights
    got = result.metrics[Config(robust_row, None, "none")].compute()
    ap, auroc = direct(truths, lambda t: weighted(t, weights, robust))
    assert got["AP"] == pytest.approx(ap, abs=1e-12) and got["AUROC"] == pytest.approx(auroc, abs=1e-12)
    got = result.metrics[Config(robust_row, "seg_felz", "mean")].compute()
    ap, _ = direct(truths, lambda t: refined_mean(weighted(t, weights, robust), t["tiles"]))
    assert got["AP"] == pytest.approx(ap, abs=1e-12)


def test_baseline_and_per_scenario(result, log_and_truth):
    truths = log_and_truth[1]
    scores = np.concatenate([t["mnad"].ravel() for _, _, t in truths])
    labels = np.concatenate([t["truth_full"].ravel() for _, _, t in truths])
    ap, auroc = sklearn_scores(scores, labels)
    baseline = result.baseline.compute()
    assert baseline["AP"] == pytest.approx(ap, abs=1e-12) and baseline["AUROC"] == pytest.approx(auroc, abs=1e-12)
    assert result.baseline_frames == 12
    assert set(result.per_scenario) == {"Scenario_a", "Scenario_b"}
    best = {}  # the second pass: per scenario, the best-AP row under each headline mask setting
    for setting in ("gt mean", "felzenszwalb mean", "no mask", "felzenszwalb mean_pixel"):
        configs = [c for c in result.metrics if result.setting_label(c) == setting]
        top = max(configs, key=lambda c: (result.metrics[c].compute()["AP"], -c.row))
        best[f"best {setting}: {result.row_label(top.row)}"] = top
    for label, config in best.items():
        both = (
            PixelMetrics()
            .merge(result.per_scenario["Scenario_a"][label])
            .merge(result.per_scenario["Scenario_b"][label])
        )
        assert both.compute()["AP"] == pytest.approx(result.metrics[config].compute()["AP"], abs=1e-12)
    assert set(result.per_scenario["Scenario_a"]) == set(best) | {
        "no mask",
        "gt mean",
        "gt max",
        "gt single",
        "gt single_keep_raw",
        "gt mean_pixel",
        "felzenszwalb mean",
        "felzenszwalb max",
        "felzenszwalb single",
        "felzenszwalb single_keep_raw",
        "felzenszwalb mean_pixel",
        "MNAD",
    }
    pooled = result.per_scenario["Scenario_a"]["no mask"]
    pooled.merge(result.per_scenario["Scenario_b"]["no mask"])
    assert pooled.compute()["AP"] == pytest.approx(
        result.metrics[Config(result.default_row, None, "none")].compute()["AP"]
    )
    assert result.default_row == 14


def test_component_metrics_of_mnad_equal_direct(result, log_and_truth):
    frames = [(t["mnad"], t["truth_full"]) for _, _, t in log_and_truth[1]]
    assert result.components["MNAD"] == component_metrics(frames)
    assert any(name.startswith("best AP") for name in result.components)


def test_diagnosis_equals_direct_computation(result, log_and_truth):
    truths = log_and_truth[1]
    diagnosis = result.diagnosis
    counts = {}
    for _, _, t in truths:  # top 1 % of 96 pixels: each frame's highest ABS pixel
        tag = int(t["semantic"][1::2, 1::2].ravel()[np.argmax(t["maps"]["diff_abs"])])
        counts[tag] = counts.get(tag, 0) + 1
    assert diagnosis["location"]["overall"]["abs"] == pytest.approx({k: v / 12 for k, v in counts.items()})
    assert diagnosis["location"]["overall"]["ssim"] == {11: 1.0}  # the top 1 % all on the sky
    assert set(diagnosis["location"]) == {"overall", "Scenario_a", "Scenario_b"}
    assert set(diagnosis["location"]["overall"]) == {
        "abs",
        "mse",
        "ssim",
        "perceptual",
        "temporal",
        "ssim_shift",
        "fused",
    }
    assert sum(diagnosis["location"]["Scenario_a"]["fused"].values()) == pytest.approx(1.0)
    assert diagnosis["first_visible"] == {"Scenario_a": 0, "Scenario_b": 0}
    assert set(diagnosis["since_visible"]) == {"fused", "gt mean", "felzenszwalb mean"}
    weights = weight_rows()[result.default_row].weights
    for run in ("Scenario_a", "Scenario_b"):
        frames = [t for r, _, t in truths if r == run]
        aurocs = [roc_auc_score(t["anomaly"].ravel(), weighted(t, weights).ravel()) for t in frames]
        (only_bin,) = diagnosis["since_visible"]["fused"][run]  # 6 frames, bins of 20
        assert (only_bin["from"], only_bin["frames"]) == (0, 6)
        assert only_bin["rank"] == pytest.approx(np.mean(aurocs), abs=1e-6)


def test_truncated_log_stops_at_last_readable_message(log_and_truth, tmp_path):
    data = log_and_truth[0].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    partial = sweep_log(cut, progress=False, overlay_frames=0)
    assert partial.stats.truncated and "truncated" in partial.stats.truncated
    assert 0 < partial.stats.frames < 12
    assert partial.stats.messages > 0


def test_weight_rows_and_frames_shared_among_processes_give_the_one_process_result(log_and_truth):
    result = sweep_log(log_and_truth[0], progress=False, overlay_frames=2)  # not the fixture: tests pool into it
    shared = sweep_log(log_and_truth[0], progress=False, overlay_frames=2, workers=3)
    assert list(shared.metrics) == list(result.metrics)  # the same configurations, met in the same order
    for config, metrics in result.metrics.items():
        assert np.array_equal(shared.metrics[config].hist, metrics.hist), config
    assert shared.frames == result.frames and shared.default_row == result.default_row
    assert shared.skipped_rows == result.skipped_rows and shared.components == result.components
    assert shared.diagnosis == result.diagnosis
    assert [(o.run, o.seq) for o in shared.overlays] == [(o.run, o.seq) for o in result.overlays]
    for run, settings in result.per_scenario.items():
        assert list(shared.per_scenario[run]) == list(settings)
        for label, metrics in settings.items():
            assert np.array_equal(shared.per_scenario[run][label].hist, metrics.hist), (run, label)


def test_report_files(result, log_and_truth, tmp_path):
    index = write_report(result, tmp_path / "report", log_and_truth[0])
    out = index.parent
    for name in (
        "results.json",
        "table.md",
        "table.csv",
        "pr_curves.png",
        "roc_curves.png",
        "per_scenario.md",
        "index.html",
        "overlay_00.png",
        "since_visible.png",
    ):
        assert (out / name).is_file(), name
    summary = json.loads((out / "results.json").read_text())
    diagnosis = summary["diagnosis"]
    assert diagnosis["top_fraction"] == 0.01 and set(diagnosis["location"]["overall"]["abs"]) <= {
        "sky",
        "road",
        "anomaly",
    }
    assert diagnosis["since_visible"]["fused"]["all"][0]["frames"] == 12
    assert len(summary["rows"]) == 17 * 11 + (11 + 28) * 5 and summary["baseline"]["name"] == "MNAD"
    assert "MNAD" in summary["components"] and (out / "components.md").is_file()
    assert {"weights", "masks", "AP", "FPR95", "AUROC", "extra"} <= set(summary["rows"][0])
    extra = {(r["weights_label"], r["masks"]) for r in summary["rows"] if r["extra"]}
    assert ("ssim+perceptual+temporal (1/3)", "gt mean") in extra and ("abs", "gt single_keep_raw") in extra
    assert ("abs", "gt max") in extra and ("abs", "felzenszwalb max") not in extra
    assert ("all (1/5), robust", "felzenszwalb mean") in extra and ("all (1/5), robust", "no mask") in extra
    table = (out / "table.md").read_text()
    assert table.count("\n| ") == 17 * 11 + (11 + 28) * 5 + 1 and "**" in table
    best_ap = max(r["AP"] for r in summary["rows"] + [summary["baseline"]])
    assert f"**{100 * best_ap:.2f}**" in table
    scenarios = (out / "per_scenario.md").read_text()
    assert "| Scenario_a | animal | ? |" in scenarios and "| Scenario_b | home | ? |" in scenarios  # no config here
    with open(out / "per_scenario.csv") as f:
        per_setting: dict[str, dict[str, float]] = {}
        for line in csv.DictReader(f):
            per_setting.setdefault(line["setting"], {})[line["scenario"]] = float(line["AUROC"])
    weakest = next(line for line in scenarios.splitlines() if line.startswith("| weakest scenario |"))
    cells = [c.strip() for c in weakest.strip("|").split("|")][3:]
    assert len(cells) == len(per_setting)
    # the CSV lists the settings in the table's order
    for cell, aurocs in zip(cells, per_setting.values(), strict=True):
        run = min(aurocs, key=aurocs.get)
        below = sum(a < 0.8 for a in aurocs.values())
        assert cell == f"AUROC {100 * aurocs[run]:.2f} ({run.removeprefix('Scenario_')}), {below} of 2 below"
    for name in ("table.md", "per_scenario.md", "components.md"):  # each table file names the PD network
        assert "PD network: label-free feature net features.safetensors" in (out / name).read_text(), name


def test_per_scenario_names_each_drives_weather(result, log_and_truth, tmp_path):
    from dataclasses import replace

    lit = replace(result, protocol={**result.protocol, "scenario_weather": {"Scenario_a": "sunset"}})
    out = write_report(lit, tmp_path / "report", log_and_truth[0]).parent
    scenarios = (out / "per_scenario.md").read_text()
    assert "| scenario | anomaly | weather |" in scenarios
    assert "| Scenario_a | animal | sunset |" in scenarios and "| Scenario_b | home | ? |" in scenarios
    with open(out / "per_scenario.csv") as f:
        lines = list(csv.DictReader(f))
    assert {(line["scenario"], line["weather"]) for line in lines} == {("Scenario_a", "sunset"), ("Scenario_b", "?")}
    weakest = next(line for line in scenarios.splitlines() if line.startswith("| weakest scenario |"))
    for cell in [c.strip() for c in weakest.strip("|").split("|")][3:]:
        assert cell == "" or "(a, sunset)" in cell or "(b)" in cell, cell


def test_protocol_reads_each_drives_weather_from_the_data_folder(tmp_path):
    from umad_replay.protocol import run_protocol

    config = tmp_path / "data" / "Scenario_Configuration_Files"
    config.mkdir(parents=True)
    (tmp_path / "data" / "anomalous").mkdir()
    entries = [{"scenario_id": "a", "weather": "sunset"}, {"scenario_id": "b", "weather": {"sun_altitude": 10}}]
    (config / "scenario_config_map_Synthetic.json").write_text(json.dumps({"scenarios": entries}))
    metadata = {"graph": GRAPH, "base_dir": str(tmp_path), "version": "test"}
    assert run_protocol(metadata, {})["scenario_weather"] == {"Scenario_a": "sunset"}  # b names no preset
    assert run_protocol({**metadata, "base_dir": str(tmp_path / "elsewhere")}, {})["scenario_weather"] == {}


def test_protocol_is_read_from_the_log_and_the_model_records(result, log_and_truth, tmp_path):
    out = write_report(result, tmp_path / "report", log_and_truth[0]).parent
    protocol = json.loads((out / "results.json").read_text())["protocol"]
    base = log_and_truth[0].parent
    assert protocol["data"] == str(base / "data/anomalous") and protocol["every"] == 5
    assert protocol["drives"] == 2 and protocol["frames"] == 12
    assert protocol["frames_evaluated"] == {"Scenario_a": list(range(6)), "Scenario_b": list(range(6))}
    assert protocol["score_resolution"] == [h, w] and protocol["label_resolution"] == [H, W]
    models = protocol["models"]
    assert models["world_model"]["trained_on"] == "/data/normal" and models["world_model"]["drives"] == 3
    assert models["perceptual"]["network"] == "label-free feature net"  # the --set in the metadata applies
    assert models["perceptual"]["trained_on"] == "/data/features-normal"
    assert models["perceptual"]["file"] == str(base / "models/features.safetensors")
    assert models["mnad"]["trained_on"] == "/data/mnad-normal"
    assert protocol["segmenters"] == {
        "seg_gt": {"method": "gt"},
        "seg_sam": {"method": "sam", "network": "SAM vit_b", "file": "/weights/sam_vit_b.pth"},
    }


def test_page_opens_with_the_headline_and_every_picture_exists(result, log_and_truth, tmp_path):
    out = write_report(result, tmp_path / "report", log_and_truth[0]).parent
    summary = json.loads((out / "results.json").read_text())
    headline = summary["headline"]
    assert [s["column"] for s in headline["settings"]] == [
        "gt",
        "unsupervised",
        "max",
        "none",
        "single",
        "unsupervised_pixel",
    ]
    gt = max(r["AP"] for r in summary["rows"] if r["masks"] == "gt mean")
    unsupervised = max(r["AP"] for r in summary["rows"] if r["masks"] == "felzenszwalb mean")
    assert headline["settings"][0]["AP"] == gt
    assert headline["ratios"]["unsupervised / GT masks (AP)"] == pytest.approx(unsupervised / gt)
    assert headline["ratios"]["UMAD / MNAD (AP)"] == pytest.approx(unsupervised / summary["baseline"]["AP"])
    felzenszwalb = [r for r in summary["rows"] if r["masks"] == "felzenszwalb mean"]
    lowest = min(felzenszwalb, key=lambda r: r["FPR95"])
    assert headline["settings"][1]["lowest_FPR95"] == {
        "weights_label": lowest["weights_label"],
        "FPR95": lowest["FPR95"],
        "AP": lowest["AP"],
    }
    assert lowest["FPR95"] < headline["settings"][1]["FPR95"]  # not the best-AP row: the choice is tested
    page = (out / "index.html").read_text()
    assert f"{100 * lowest['FPR95']:.2f} ({lowest['weights_label']}; AP {100 * lowest['AP']:.2f})" in page
    order = [
        'class="headline">Data ' + str(log_and_truth[0].parent / "data/anomalous"),
        "UMAD / MNAD (AP)",
        "AP by weights and mask settings",
        "<img",
        "Ablation table",
        "Per scenario",
        "Diagnosis: where the error lives",
        "Component metrics",
    ]
    positions = [page.index(text) for text in order]
    assert positions == sorted(positions)
    assert "PD network: label-free feature net features.safetensors (trained on /data/features-normal)" in page
    assert "pixels scored at 8×12 (model resolution; labels 16×24 resized nearest)" in page
    assert "masks: gt, SAM vit_b sam_vit_b.pth." in page
    assert f'class="best num">{100 * gt:.2f}<' in page and "paper (AnoVox" in page
    pictures = re.findall(r'src="([^"]+)"', page)
    assert "pr_curves.png" in pictures and all((out / p).is_file() for p in pictures)
    assert "<script" not in page and "http" not in page.replace("http-equiv", "")
    markdown = (out / "index.md").read_text()
    assert markdown.index("UMAD / MNAD (AP)") < markdown.index("## AP by weights") < markdown.index("## Ablation")
    assert "| map | " in markdown and "| Scenario_a | 0 | " in markdown  # location and since-visible tables
    assert all((out / p).is_file() for p in re.findall(r"\]\(([^)]+)\)", markdown))


def test_paper_layout_table(result, tmp_path):
    out = write_report(result, tmp_path / "report", layout="paper").parent
    lines = (out / "table.md").read_text().splitlines()
    header = lines[0]
    assert header.index("gt mean AP") < header.index("felzenszwalb mean AP") < header.index("felzenszwalb max AP")
    assert header.index("felzenszwalb max AP") < header.index("no mask AP") < header.index("felzenszwalb single AP")
    rows = [line for line in lines[2:] if line.startswith("| ")]
    assert len(rows) == 56 and rows[0].startswith("| 1 |  |  |  |  |  |  | paper |")  # the lidar rows: no lidar map
    assert all("| extra |" in row for row in rows[15:28]) and rows[17].startswith("|  |  |  |  |  | 1 |  | extra |")
    assert all("| extra, robust |" in row for row in rows[28:]) and rows[28].startswith(
        "| 1 |  |  |  |  |  |  | extra, robust |"
    )


def test_cli(log_and_truth, tmp_path, capsys):
    assert (
        umad_main(["sweep", str(log_and_truth[0]), "--out", str(tmp_path / "r"), "--overlays", "1", "--every", "2"])
        == 0
    )
    summary = json.loads((tmp_path / "r" / "results.json").read_text())
    assert {r["frames"] for r in summary["rows"]} == {6}
    assert summary["protocol"]["sweep_every"] == 2 and summary["protocol"]["frames"] == 6
    assert umad_main(["sweep", str(log_and_truth[0]), "--out", str(tmp_path / "p"), "--layout", "paper"]) == 0
    assert json.loads((tmp_path / "p" / "results.json").read_text())["protocol"]["layout"] == "paper"


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        ([], (2, "long")),
        (["--protocol", "paper"], (10, "paper")),
        (["--protocol", "paper", "--every", "5"], (5, "paper")),
    ],
)
def test_eval_protocols(argv, expected):
    args = build_parser().parse_args(["eval", *argv])
    assert every_and_layout(args.protocol, args.every) == expected


def test_sparse_seqs_and_late_parts_complete_by_frame_count(tmp_path):
    """Seqs 0, 10, 20, ... (every 10th frame) with each frame's truth arriving two frames late."""
    frames = list(synthetic_frames(runs=("r",), n=6, seed=1))
    path = tmp_path / "sparse.mcap"
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.NONE)
        writer.start(profile="umad", library="test")
        channels, delayed = {}, []
        for _, seq, msgs, _ in frames:
            for op, output, arrays, meta in msgs:
                item = (op, output, Message("r", 10 * seq, 0, op, meta, arrays))
                if output == "truth":
                    delayed.append(item)
                else:
                    _write(writer, channels, *item)
            while len(delayed) > 2:
                _write(writer, channels, *delayed.pop(0))
        for item in delayed:
            _write(writer, channels, *item)
        writer.finish()
    result = sweep_log(path, lag=3, progress=False, overlay_frames=0, components=False)
    assert result.stats.frames == 6 and result.stats.late == 0
    assert set(result.frames.values()) == {6}


def _write(writer, channels, op, output, msg):
    key = f"umad/test/{op}/{output}"
    if key not in channels:
        channels[key] = writer.register_channel(key, "msgpack", 0)
    writer.add_message(channels[key], msg.seq, encode(msg), msg.seq, msg.seq)


@pytest.mark.parametrize("seed", range(4))
def test_mask_set_is_bit_identical_to_refine(seed):
    rng = np.random.default_rng(seed)
    fused = rng.random((24, 36)).astype(np.float32)
    fused[:4, :4] = 0.5  # ties inside and across masks
    overlapping = rng.random((9, 24, 36)) < 0.2
    overlapping[3] = False  # an empty mask
    overlapping[5] = overlapping[6]  # two equal masks: equal scores
    tiling = np.stack([(np.arange(36)[None, :] // 6 == k).repeat(24, axis=0) for k in range(6)])
    coarse = np.round(fused * 1024) / 1024  # multiples of 2**-10: every mask's sum is exact
    tiny = fused.copy()
    tiny[:, ::5] = 1e-30  # in every mask: no exact sums, refine's product
    peaked = np.full((24, 36), 2.0**-30, np.float32)  # a tile's sum is exact though area x largest is not
    peaked[0, ::6] = 0.25  # one peak per tile: sum 0.25 + 143 * 2**-30 < 2**52 * spacing(2**-30) = 0.5 < 144 * 0.25
    for masks in (overlapping, tiling, np.zeros((0, 24, 36), bool)):
        mask_set = MaskSet(masks)
        for score_map in (fused, coarse, tiny, peaked):
            refined = mask_set.refine_all(score_map)
            for mode in REFINE_MODES:
                expected = refine(score_map, masks, mode=mode, uncovered="keep")
                assert refined[mode].dtype == expected.dtype and np.array_equal(refined[mode], expected), mode
        if mask_set.nonempty.size:
            pixel_values = {
                name: m.astype(np.float64).reshape(-1)[mask_set.pixels]
                for name, m in (("coarse", coarse), ("tiny", tiny))
            }
            assert mask_set.exact_sums(pixel_values["coarse"]) is not None
            assert mask_set.exact_sums(pixel_values["tiny"]) is None
    peaked_values = peaked.astype(np.float64).reshape(-1)[MaskSet(tiling).pixels]
    assert MaskSet(tiling).exact_sums(peaked_values) is not None


SHIPPED_GRAPH = """
name: test
operators:
  - {id: replayer, kind: replayer, params: {source: data/anomalous}}
  - {id: fusion, kind: fusion, inputs: {maps: diff_*/map}, params: {weights: {abs: 0.5, ssim: 0.5, perceptual: 0.0}}}
  - {id: seg_gt, kind: segmenter, inputs: {frame: world_model/frame, truth: replayer/truth}, params: {method: gt}}
  - {id: refine_gt, kind: mask_refiner, inputs: {fused: fusion/fused, masks: seg_gt/masks}, params: {mode: mean}}
  - {id: seg_felz, kind: segmenter, inputs: {frame: world_model/frame}, params: {method: felzenszwalb}}
  - {id: refine_felz, kind: mask_refiner, inputs: {fused: fusion/fused, masks: seg_felz/masks}, params: {mode: mean}}
"""


def test_the_shipped_configuration_is_scored_and_leads_the_report(tmp_path):
    path = tmp_path / "run.mcap"
    truths = write_log(path, synthetic_frames(), {"graph": SHIPPED_GRAPH, "base_dir": str(tmp_path), "version": "t"})
    result = sweep_log(path, progress=False, overlay_frames=0)
    # abs + ssim at 1/2 is no row of the table: it is added, every refinement scored; the first
    # label-free refiner (not the ground truth's) is what the graph shipped
    assert result.rows[-1].weights == {"abs": Fraction(1, 2), "ssim": Fraction(1, 2)} and result.rows[-1].extra
    assert result.shipped.row == len(result.rows) - 1
    assert (result.shipped.segmenter, result.shipped.mode) == ("seg_felz", "mean")
    expected = direct(truths, lambda t: refined_mean(weighted(t, {"abs": 0.5, "ssim": 0.5}), t["tiles"]))
    scores = result.metrics[result.shipped].compute()
    assert (scores["AP"], scores["AUROC"]) == pytest.approx(expected, abs=2e-3)
    name = "shipped: felzenszwalb mean: abs+ssim (1/2)"
    assert result.shipped_name() == name and set(result.per_scenario["Scenario_a"]) >= {name}

    out = write_report(result, tmp_path / "report", path).parent
    summary = json.loads((out / "results.json").read_text())
    shipped = summary["headline"]["shipped"]
    assert (shipped["masks"], shipped["weights_label"], shipped["refiner"]) == (
        "felzenszwalb mean",
        "abs+ssim (1/2)",
        "refine_felz",
    )
    assert shipped["AP"] == pytest.approx(scores["AP"]) and set(shipped["per_drive_AUROC"]) == {
        "Scenario_a",
        "Scenario_b",
    }
    weakest = min(shipped["per_drive_AUROC"], key=shipped["per_drive_AUROC"].get)
    assert shipped["weakest"]["drive"] == weakest
    assert summary["headline"]["ratios"]["shipped / MNAD (AP)"] == pytest.approx(
        shipped["AP"] / summary["baseline"]["AP"]
    )
    index = (out / "index.md").read_text()
    assert index.index("as the graph ran (refine_felz)") < index.index("chosen on the test data after the fact")
    assert f"{name} AP / FPR95 / AUROC" in (out / "per_scenario.md").read_text()

    b = tmp_path / "b"
    assert umad_main(["compare", str(out), str(out), "--out", str(b)]) == 0
    assert "shipped masks A / B" in (b / "compare.md").read_text()


def graph_with_lidar(extras: dict) -> str:
    """SHIPPED_GRAPH fusing a lidar map too, with fusion's `extras` (e.g. above_lidar_weight)."""
    params = ", ".join(["weights: {abs: 0.5, ssim: 0.5, lidar: 0.5}", *(f"{k}: {v}" for k, v in extras.items())])
    return SHIPPED_GRAPH.replace("params: {weights: {abs: 0.5, ssim: 0.5, perceptual: 0.0}}", f"params: {{{params}}}")


def with_lidar_maps(frames, seed=7):
    """`frames` with a lidar difference map each, marking its top three rows as above the lidar's returns."""
    rng = np.random.default_rng(seed)
    above = np.zeros((h, w), np.uint8)
    above[:3] = 1
    for run, seq, msgs, truth in frames:
        lidar = rng.random((h, w)).astype(np.float32)
        truth["lidar_message"] = Message(
            run, seq, meta={"metric": "lidar"}, arrays={"map": lidar, "above_returns": above}
        )
        yield run, seq, [*msgs, ("diff_lidar", "map", truth["lidar_message"].arrays, {"metric": "lidar"})], truth


@pytest.mark.parametrize(
    ("extras", "note"),
    [
        ({"above_lidar_weight": 0.25}, ", camera ×0.25 above the lidar"),
        (
            {"above_lidar_weight": 0.25, "lidar_camera_exponent": 0.5},
            ", camera ×0.25 above the lidar, lidar × camera^0.5",
        ),
    ],
)
def test_the_shipped_row_fuses_the_lidar_map_as_the_fusion_operator_does(tmp_path, extras, note):
    from umad_common.dataflow import Frame
    from umad_operators.fusion import Fusion

    path = tmp_path / "run.mcap"
    metadata = {"graph": graph_with_lidar(extras), "base_dir": str(tmp_path), "version": "t"}
    truths = write_log(path, with_lidar_maps(synthetic_frames()), metadata)
    result = sweep_log(path, progress=False, overlay_frames=0, components=False)
    shipped_row = result.rows[result.shipped.row]
    assert shipped_row.above_lidar_weight == extras["above_lidar_weight"]
    assert shipped_row.lidar_camera_exponent == extras.get("lidar_camera_exponent", 0.0)
    assert result.row_label(result.shipped.row) == "abs+ssim (1/2) + lidar 1/3" + note

    def graph_map(t, extras):
        fusion = Fusion({"weights": {"abs": 0.5, "ssim": 0.5, "lidar": 0.5}, **extras})
        maps = {
            op: Message("r", 0, meta={"metric": METRIC_OPS[op]}, arrays={"map": t["maps"][op]})
            for op in ("diff_abs", "diff_ssim")
        }
        maps["diff_lidar"] = t["lidar_message"]
        fused = fusion.process(Frame("r", 0, 0, many={"maps": maps}))["fused"].arrays["map"]
        return refined_mean(fused, t["tiles"])

    scores = result.metrics[result.shipped].compute()
    assert (scores["AP"], scores["AUROC"]) == pytest.approx(direct(truths, lambda t: graph_map(t, extras)), abs=2e-3)
    plain = direct(truths, lambda t: graph_map(t, {}))
    assert (scores["AP"], scores["AUROC"]) != pytest.approx(plain, abs=2e-3)  # the extras change the figures


def test_a_shipped_configuration_that_is_a_row_of_the_table_adds_none():
    from umad_replay.configurations import shipped_row_index, with_shipped_row

    shipped = {"weights": dict.fromkeys(("abs", "mse", "ssim", "perceptual", "temporal"), 0.2), "mode": "max"}
    rows = weight_rows()
    assert (
        with_shipped_row(rows, shipped) == rows and rows[shipped_row_index(rows, shipped)].weights == rows[14].weights
    )
    lidar = {"weights": {**shipped["weights"], "lidar": 0.5}, "mode": "mean_pixel"}  # the default graph's
    assert weights_label(rows[shipped_row_index(rows, lidar)].weights) == "all (1/5) + lidar 1/3"
    assert len(with_shipped_row(rows, {**lidar, "mode": "max"})) == len(rows) + 1  # max is not scored on lidar rows
