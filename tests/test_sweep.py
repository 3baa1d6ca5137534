"""`umad sweep` on a small synthetic MCAP log written here with the mcap Writer, checked against a
direct computation with numpy + scikit-learn; a truncated log; the report files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer
from sklearn.metrics import average_precision_score, roc_auc_score

from replay.sweep import Config, MaskSet, paper_weight_rows, sweep_log
from umad_common.cli import main as umad_main
from umad_common.messages import Message, encode
from umad_common.metrics.components import component_metrics
from umad_common.refine import refine
from umad_common.viz.report import write_report

H, W, h, w = 16, 24, 8, 12  # camera / truth size, model size
METRIC_OPS = {"diff_abs": "abs", "diff_mse": "mse", "diff_ssim": "ssim", "diff_pd": "perceptual", "diff_td": "td"}


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
            gt = np.stack([small == 1, small != 1])
            mnad = rng.random((H, W)).astype(np.float32) + anomaly
            tiles = np.stack([np.zeros((h, w), bool) for _ in range(4)])
            for k in range(4):
                tiles[k, :, 3 * k : 3 * k + 3] = True
            msgs = [
                (
                    "replayer",
                    "truth",
                    # run a shows a CARLA `animal` (30), run b a `home` (29) object
                    {
                        "anomaly": anomaly,
                        "instance": anomaly.astype(np.int32),
                        "semantic": ((anomaly == 1) * (30 - runs.index(run))).astype(np.uint8),
                    },
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
                {"anomaly": small, "maps": maps, "gt": gt, "tiles": tiles, "truth_full": anomaly, "mnad": mnad},
            )


def write_log(path, frames):
    truths = []
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.NONE, chunk_size=4096)
        writer.start(profile="umad", library="test")
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


@pytest.fixture(scope="module")
def log_and_truth(tmp_path_factory):
    path = tmp_path_factory.mktemp("log") / "run.mcap"
    truths = write_log(path, synthetic_frames())
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


def weighted(t, weights):
    metric_to_op = {("temporal" if m == "td" else m): op for op, m in METRIC_OPS.items()}
    return sum(float(wt) * t["maps"][metric_to_op[m]] for m, wt in weights.items()) / sum(
        float(v) for v in weights.values()
    )


def refined_mean(fused, masks):
    out = fused.copy()
    for mask in masks:  # tiling masks: no overlaps
        out[mask] = fused[mask].mean()
    return out


def test_rows_and_settings(result):
    rows = paper_weight_rows()
    assert len(rows) == 15 and len({tuple(sorted(r)) for r in rows}) == 15
    assert result.stats.segmenters == {"seg_gt": "gt", "seg_felz": "felzenszwalb"}
    assert len(result.metrics) == 15 * 7 and not result.skipped_rows
    assert result.stats.frames == 12 and result.stats.duplicates == 2 and result.stats.bad == 6
    assert result.stats.truncated is None
    assert set(result.frames.values()) == {12}


@pytest.mark.parametrize("row", [0, 4, 5, 14])
def test_numbers_equal_direct_computation(result, log_and_truth, row):
    truths = log_and_truth[1]
    weights = paper_weight_rows()[row]
    got = result.metrics[Config(row, None, "none")].compute()
    ap, auroc = direct(truths, lambda t: weighted(t, weights))
    assert got["AP"] == pytest.approx(ap, abs=1e-12) and got["AUROC"] == pytest.approx(auroc, abs=1e-12)
    got = result.metrics[Config(row, "seg_felz", "mean")].compute()
    ap, auroc = direct(truths, lambda t: refined_mean(weighted(t, weights), t["tiles"]))
    assert got["AP"] == pytest.approx(ap, abs=1e-12) and got["AUROC"] == pytest.approx(auroc, abs=1e-12)
    got = result.metrics[Config(row, "seg_gt", "single")].compute()
    ap, _ = direct(truths, lambda t: refined_mean(weighted(t, weights), t["gt"][[0]]))  # the anomaly mask wins
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
    assert set(result.per_scenario["Scenario_a"]) == {
        "no mask",
        "gt mean",
        "gt max",
        "gt single",
        "felzenszwalb mean",
        "felzenszwalb max",
        "felzenszwalb single",
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


def test_truncated_log_stops_at_last_readable_message(log_and_truth, tmp_path):
    data = log_and_truth[0].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    partial = sweep_log(cut, progress=False, overlay_frames=0)
    assert partial.stats.truncated and "truncated" in partial.stats.truncated
    assert 0 < partial.stats.frames < 12
    assert partial.stats.messages > 0


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
    ):
        assert (out / name).is_file(), name
    summary = json.loads((out / "results.json").read_text())
    assert len(summary["rows"]) == 105 and summary["baseline"]["name"] == "MNAD"
    assert "MNAD" in summary["components"] and (out / "components.md").is_file()
    assert {"weights", "masks", "AP", "FPR95", "AUROC"} <= set(summary["rows"][0])
    table = (out / "table.md").read_text()
    assert table.count("\n| ") == 106 and "**" in table
    best_ap = max(r["AP"] for r in summary["rows"] + [summary["baseline"]])
    assert f"**{100 * best_ap:.2f}**" in table
    page = (out / "index.html").read_text()  # the page shows the table files' values and marks
    assert f"<b>{100 * best_ap:.2f}</b>" in page and "<i>" in page and "_mark" not in page
    assert page.count("<table>") == 3  # ablation, components, per scenario
    scenarios = (out / "per_scenario.md").read_text()
    assert "| Scenario_a | animal |" in scenarios and "| Scenario_b | home |" in scenarios


def test_cli(log_and_truth, tmp_path, capsys):
    assert (
        umad_main(["sweep", str(log_and_truth[0]), "--out", str(tmp_path / "r"), "--overlays", "1", "--every", "2"])
        == 0
    )
    summary = json.loads((tmp_path / "r" / "results.json").read_text())
    assert {r["frames"] for r in summary["rows"]} == {6}


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
    for masks in (overlapping, tiling, np.zeros((0, 24, 36), bool)):
        refined = MaskSet(masks).refine_all(fused)
        for mode in ("mean", "max", "single"):
            expected = refine(fused, masks, mode=mode, uncovered="keep")
            assert refined[mode].dtype == expected.dtype and np.array_equal(refined[mode], expected), mode
