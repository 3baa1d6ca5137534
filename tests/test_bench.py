"""`umad bench`: the in-process benches run from the command line and report both sides of each ratio."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from umad_common.benchmarks.blobs import checksum
from umad_common.benchmarks.bus import against_dora
from umad_common.benchmarks.dora_relay import dora_missing, over_dora
from umad_common.cli import main as umad_main


def test_metrics_bench_agrees_with_scikit_learn(tmp_path):
    out = tmp_path / "bench.json"
    assert umad_main(["bench", "metrics", "--pixels", "200000", "--out", str(out)]) == 0
    result = json.loads(out.read_text())["metrics"]
    assert result["max_abs_difference"] < 1e-9
    assert result["umad"]["AP"] == pytest.approx(result["sklearn"]["AP"], abs=1e-9)
    assert result["speedup"] > 0 and result["memory_ratio"] > 0
    assert "| metrics | speedup |" in out.with_suffix(".md").read_text()


def test_differences_and_predictors_benches_measure_every_metric_and_both_models(tmp_path):
    out = tmp_path / "bench.json"
    assert umad_main(["bench", "differences", "--frames", "2", "--out", str(out)]) == 0
    differences = json.loads(out.read_text())["differences"]
    assert set(differences["fps"]) == {"abs", "mse", "ssim", "ssim_shift", "perceptual", "temporal", "lidar"}
    assert differences["fps_ratio_to_abs"]["abs"] == 1.0
    assert all(v > 0 for v in differences["fps"].values())

    assert umad_main(["bench", "predictors", "--frames", "6", "--out", str(out)]) == 0
    predictors = json.loads(out.read_text())["predictors"]
    assert predictors["frames"] == 6
    assert all(predictors[f"threads_{n}"][k] > 0 for n in (1, 2) for k in ("world_model_fps", "mnad_fps"))


def test_bus_bench_measures_the_runtime_against_bare_zenoh_one_process_and_a_secured_hub(tmp_path, hub_endpoint):
    """All sides of the bus bench run on a loopback hub and come back in the report."""
    out = tmp_path / "bench.json"
    assert umad_main(["bench", "bus", "--frames", "24", "--hub", hub_endpoint, "--out", str(out)]) == 0
    bus = json.loads(out.read_text())["bus"]
    sides = ("bare_zenoh_window_8", "bus_window_8", "bus_window_8_zenoh_shm", "bus_window_8_through_zenoh")
    sides += ("bus_window_8_through_hub",)
    for side in ("in_process", *sides, "bus_window_1"):
        assert bus[side]["fps"] > 0 and bus[side]["cpu_ms_per_frame"] > 0, side
        assert bus[side]["p99_ms"] >= bus[side]["p50_ms"] > 0, side
    assert bus["fps_ratio_bus_through_zenoh_over_bare_zenoh"] == pytest.approx(
        bus["bus_window_8_through_zenoh"]["fps"] / bus["bare_zenoh_window_8"]["fps"]
    )
    assert len(bus["fps_ratio_bus_through_zenoh_over_bare_zenoh_per_round"]) == 3
    assert bus["fps_ratio_bus_over_bus_through_zenoh"] == pytest.approx(
        bus["bus_window_8"]["fps"] / bus["bus_window_8_through_zenoh"]["fps"]
    )
    assert bus["fps_ratio_bus_over_bus_through_hub"] == pytest.approx(
        bus["bus_window_8"]["fps"] / bus["bus_window_8_through_hub"]["fps"]
    )
    assert "| bus | bare_zenoh_window_8.fps |" in out.with_suffix(".md").read_text()
    security = bus["security"]
    for mode in ("tcp", "mtls", "mtls_acl"):
        side = security[f"through_sockets_{mode}"]
        assert side["fps"] > 0 and side["cpu_ms_per_frame"] > 0 and side["hub_cpu_ms_per_frame"] > 0, mode
    assert security["fps_ratio_mtls_acl_over_tcp"] == pytest.approx(
        security["through_sockets_mtls_acl"]["fps"] / security["through_sockets_tcp"]["fps"]
    )
    assert len(security["fps_ratio_mtls_acl_over_tcp_per_round"]) == security["rounds"] == 3


def test_the_bench_relay_reads_every_byte():
    data = np.zeros(4099, np.uint8)
    for where in (0, 4096, 4098):  # a page's start, beyond `data[::4096]`'s reach, in the 8-byte tail
        touched = data.copy()
        touched[where] = 1
        assert checksum(touched) == 1
    assert checksum(np.full(16, 255, np.uint8)) == 2 * 0xFFFFFFFFFFFFFFFF % (1 << 64)


def test_against_dora_without_dora_rs_says_so_in_one_line_and_nothing_else(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "dora", None)  # as if not installed
    assert against_dora(10, 1 << 10, {"fps": 1.0, "cpu_ms_per_frame": 1.0}) == {
        "dora_window_8": "dora-rs is not installed (pip install 'umad[dora]'): the relay against dora-rs is not run"
    }
    assert capsys.readouterr().out.count("\n") == 1


@pytest.mark.skipif(dora_missing() is not None, reason="dora-rs is not installed (the `dora` extra)")
def test_the_dora_relay_acks_every_frame_when_lossless():
    result = over_dora(frames=40, size_bytes=1 << 16, window=8)
    assert result["lost_frames"] == 0 and result["fps"] > 0 and result["cpu_ms_per_frame"] > 0


@pytest.mark.slow
def test_record_bench_runs_the_default_graph_with_and_without_a_recording(hub_endpoint):
    from umad_common.benchmarks.record import bench_record

    result = bench_record(frames=3, pairs=1, hub=hub_endpoint)
    assert result["fps_plain"] > 0 and result["fps_recorded"] > 0
    assert result["fps_ratio_recorded"] == pytest.approx(result["fps_recorded"] / result["fps_plain"])
    assert result["complete"] and result["log_messages"] == 20 * 4  # 20 channels, 3 frames and the end marker
    assert result["log_mib_per_frame"] > 0


def test_train_bench_refuses_to_compare_one_process_with_itself():
    from umad_common.benchmarks.train import bench_train

    with pytest.raises(ValueError, match="--nproc 1: the bench compares one process with more"):
        bench_train(processes=1)


def test_data_bench_reads_the_same_drive_from_a_bag_and_from_anovox_folders(tmp_path):
    out = tmp_path / "bench.json"
    assert umad_main(["bench", "data", "--frames", "3", "--out", str(out)]) == 0
    data = json.loads(out.read_text())["data"]
    assert data["frames"] == 3 and data["same_rgb"] and data["same_lidar"]
    for ratio in ("fps_ratio_bag", "fps_ratio_bag_label_free"):
        assert data[ratio] > 0
    assert data["fps_ratio_bag"] == pytest.approx(data["fps_bag"] / data["fps_anovox"])
