"""The accumulator operator: per-run and overall metrics, label resize, dedup, final JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest

from umad_common.dataflow import Context, Frame
from umad_common.dataflow.api.messages import Message
from umad_common.metrics.pixel import PixelMetrics
from umad_common.refine import resize_nearest
from umad_operators.accumulator import Accumulator


def make_frame(run, seq, labels, maps):
    truth = Message(run, seq, arrays={"anomaly": labels})
    scores = {p: Message(run, seq, producer=p, arrays={"map": m}) for p, m in maps.items()}
    return Frame(run, seq, 0, inputs={"truth": truth}, many={"scores": scores})


def frames(seed, runs=("a", "b"), n=3):
    rng = np.random.default_rng(seed)
    for run in runs:
        for seq in range(n):
            labels = np.zeros((16, 24), np.uint8)
            labels[4:8, 6:12] = 1
            labels[0, :] = 255
            fused = rng.random((8, 12)).astype(np.float32) + 0.5 * resize_nearest(labels, (8, 12)).astype(bool)
            mnad = rng.random((16, 24)).astype(np.float32)
            yield run, seq, labels, {"fusion": fused, "mnad": mnad}


def test_overall_and_per_run_match_direct_pooling(tmp_path):
    acc = Accumulator({"out": "results/metrics.json"}, Context(base_dir=tmp_path))
    direct = {"fusion": PixelMetrics(), "mnad": PixelMetrics()}
    run_a = PixelMetrics()
    for run, seq, labels, maps in frames(0):
        out = acc.process(make_frame(run, seq, labels, maps))
        for p, m in maps.items():
            direct[p].update(m, resize_nearest(labels, m.shape))
            if run == "a" and p == "fusion":
                run_a.update(m, resize_nearest(labels, m.shape))
        assert out["metrics"].meta["run"] == run
        if run == "a" and seq == 2:
            final_a = acc.end_run("a")["metrics"].meta
    final_b = acc.end_run("b")["metrics"].meta
    assert final_a["final"] and final_a["per_run"]["fusion"]["AP"] == pytest.approx(run_a.compute()["AP"])
    for p in direct:
        assert final_b["overall"][p]["AP"] == pytest.approx(direct[p].compute()["AP"])
        assert final_b["overall"][p]["AUROC"] == pytest.approx(direct[p].compute()["AUROC"])
    written = json.loads((tmp_path / "results/metrics.json").read_text())
    assert set(written["runs"]) == {"a", "b"}
    assert written["overall"]["fusion"]["FPR95"] == pytest.approx(direct["fusion"].compute()["FPR95"])
    assert written["overall"]["mnad"]["n_anomaly"] == 3 * 2 * 4 * 6


def test_duplicates_are_counted_once():
    acc = Accumulator()
    items = list(frames(1, runs=("a",)))
    for run, seq, labels, maps in items + items[:2]:
        acc.process(make_frame(run, seq, labels, maps))
    meta = acc.end_run("a")["metrics"].meta
    assert meta["frames"] == 3
    assert meta["per_run"]["mnad"]["n_anomaly"] == 3 * 4 * 6


def test_publish_period_and_undefined_metrics_are_none():
    acc = Accumulator({"every": 2})
    labels = np.zeros((4, 4), np.uint8)
    outs = [acc.process(make_frame("r", s, labels, {"m": np.random.rand(4, 4)})) for s in range(4)]
    assert [bool(o) for o in outs] == [False, True, False, True]
    assert outs[1]["metrics"].meta["per_run"]["m"]["AP"] is None


def test_bad_map_is_refused():
    acc = Accumulator()
    with pytest.raises(ValueError, match="expected \\(h, w\\)"):
        acc.process(make_frame("r", 0, np.zeros((4, 4), np.uint8), {"m": np.zeros((4, 4, 3), np.float32)}))
