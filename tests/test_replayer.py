"""The replayer source: topics per the contract, runs and seqs, sampling, filtering, both layouts."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from umad_common.dataflow.api.messages import Message, decode, encode
from umad_common.dataflow.api.operator import Context, load_operator_class
from umad_common.datasets.anovox import AnoVoxScenario, write_benchmark_scenario
from umad_common.datasets.drive import DatasetError
from umad_common.datasets.formats import find_drives
from umad_common.datasets.synthetic.generator import generate_benchmark
from umad_operators.replayer import Replayer


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth")
    generate_benchmark(out, normal=1, anomalous=1, frames=6, seed=3, size=(96, 64))
    return out


def test_kind_is_registered():
    assert load_operator_class("replayer") is Replayer


def test_frames_follow_the_topic_contract(generated):
    frames = list(Replayer({"source": str(generated)}).frames())
    scenarios = find_drives(generated)
    assert [f.run for f in frames] == [p.name for p in scenarios for _ in range(6)]
    assert [f.seq for f in frames] == list(range(6)) * 2
    assert [f.stamp_ns for f in frames[:3]] == [0, 100_000_000, 200_000_000]
    frame = frames[7]
    out = frame.outputs
    assert set(out) == {"camera", "lidar", "ego", "route", "truth"}
    rgb = out["camera"].arrays["rgb"]
    assert rgb.shape == (64, 96, 3) and rgb.dtype == np.uint8
    assert out["camera"].meta == {"frame_id": AnoVoxScenario(scenarios[1]).frame_ids[1], "scenario": scenarios[1].name}
    points = out["lidar"].arrays["points"]
    assert points.ndim == 2 and points.shape[1] == 4 and points.dtype == np.float32 and len(points) > 1000
    ego = out["ego"].arrays["ego"]
    assert ego.shape == (4,) and ego.dtype == np.float32 and ego[0] > 0
    assert out["route"].arrays["route"].shape == (192, 192) and out["route"].arrays["route"].dtype == np.uint8
    truth = out["truth"].arrays
    assert (
        truth["anomaly"].dtype == np.uint8
        and truth["anomaly"].shape == (64, 96)
        and set(np.unique(truth["anomaly"])) <= {0, 1}
    )
    assert truth["instance"].dtype == np.int32 and truth["semantic"].dtype == np.uint8
    for output in out.values():  # every topic survives the wire format
        decoded = decode(encode(Message(frame.run, frame.seq, frame.stamp_ns, "replayer", output.meta, output.arrays)))
        for name, array in output.arrays.items():
            np.testing.assert_array_equal(decoded.arrays[name], array)


def test_anomalous_run_carries_anomaly_truth(generated):
    replayer = Replayer({"source": str(generated / "anomalous")})
    totals = [int(f.outputs["truth"].arrays["anomaly"].sum()) for f in replayer.frames()]
    assert sum(totals) > 0
    normal = Replayer({"source": str(generated / "normal")})
    assert all(f.outputs["truth"].arrays["anomaly"].sum() == 0 for f in normal.frames())


def test_every_max_frames_and_scenario_filter(generated):
    name = find_drives(generated / "normal")[0].name
    frames = list(Replayer({"source": str(generated), "every": 2, "max_frames": 2, "scenarios": [name]}).frames())
    ids = AnoVoxScenario(generated / "normal" / name).frame_ids
    assert [(f.run, f.seq) for f in frames] == [(name, 0), (name, 1)]
    assert [f.outputs["camera"].meta["frame_id"] for f in frames] == [ids[0], ids[2]]
    assert [f.stamp_ns for f in frames] == [0, 200_000_000]


def test_score_every_marks_the_frames_nobody_scores(generated):
    name = find_drives(generated / "anomalous")[0].name
    replayer = Replayer({"source": str(generated / "anomalous"), "score_every": 3, "scenarios": [name]})
    frames = list(replayer.frames())
    assert [f.seq for f in frames] == list(range(len(AnoVoxScenario(generated / "anomalous" / name))))
    for f in frames:
        skipped = [bool(out.meta.get("skip")) for out in f.outputs.values()]
        assert skipped == [f.seq % 3 != 0] * len(skipped), f.seq
        assert ("anomaly" in f.outputs["truth"].arrays) == (f.seq % 3 == 0)  # no labels for an unscored frame
        assert f.outputs["camera"].arrays["rgb"].size > 0  # the world model still needs the camera


def test_single_scenario_folder_and_relative_source(generated):
    folder = find_drives(generated / "anomalous")[0]
    replayer = Replayer({"source": f"anomalous/{folder.name}"}, Context(base_dir=generated))
    assert list(replayer.scenarios) == [folder.name]


def test_frame_at_repeats_what_frames_yielded(generated):
    replayer = Replayer({"source": str(generated), "every": 2})
    frames = list(replayer.frames())
    again = replayer.frame_at(frames[4].run, frames[4].seq)
    assert (again.run, again.seq, again.stamp_ns) == (frames[4].run, frames[4].seq, frames[4].stamp_ns)
    for port, output in frames[4].outputs.items():
        assert again.outputs[port].meta == output.meta
        for name, array in output.arrays.items():
            np.testing.assert_array_equal(again.outputs[port].arrays[name], array)
    with pytest.raises(IndexError):
        replayer.frame_at(frames[0].run, 3)
    with pytest.raises(KeyError):
        replayer.frame_at("Scenario_other", 0)


def test_benchmark_layout_and_missing_modalities(tmp_path, generated):
    source = AnoVoxScenario(find_drives(generated / "anomalous")[0])
    write_benchmark_scenario(source, tmp_path / "bench", source.name)
    frames = list(Replayer({"source": str(tmp_path / "bench")}).frames())
    assert len(frames) == 6
    out = frames[0].outputs
    np.testing.assert_array_equal(out["lidar"].arrays["points"], source[0].lidar)
    assert not out["route"].arrays["route"].any() and not out["ego"].arrays["ego"].any()
    assert out["truth"].arrays["instance"].shape == (64, 96)

    copy = Path(shutil.copytree(source.path, tmp_path / "gen" / source.name))
    for folder in copy.iterdir():
        if folder.name.startswith(("LIDAR", "ROUTE_MAP")):
            shutil.rmtree(folder)
    out = next(Replayer({"source": str(copy)}).frames()).outputs
    assert out["lidar"].arrays["points"].shape == (0, 4) and out["lidar"].arrays["points"].dtype == np.float32
    assert out["route"].arrays["route"].shape == (192, 192)


def test_bad_sources_fail_at_construction(tmp_path, generated):
    with pytest.raises(DatasetError, match="no drives found"):
        Replayer({"source": str(tmp_path)})
    with pytest.raises(DatasetError, match="no such folder"):
        Replayer({"source": str(tmp_path / "absent")})
    with pytest.raises(DatasetError, match="Scenario_nope"):
        Replayer({"source": str(generated), "scenarios": ["Scenario_nope"]})
    with pytest.raises(ValidationError):
        Replayer({"source": str(generated), "speed": 2})
    with pytest.raises(ValidationError):
        Replayer({"source": str(generated), "every": 0})
    with pytest.raises(ValidationError):
        Replayer({"source": str(generated), "pacing": "fast"})
