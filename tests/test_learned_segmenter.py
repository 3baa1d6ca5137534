"""The label-free segment net and the `learned` / `geometry_learned` segmenters: training on a tiny
fabricated drive set (deterministic, record with the command), segments that tile the frame, the
small-region merge, clear errors for bad weight files, the README recipe equal to the shipped
net's record, and a runtime switch to a method whose input is not wired refused with the reason."""

from __future__ import annotations

import argparse
import json
import shlex
import threading

import numpy as np
import pytest
import torch

from tests.test_segmenter import H, W, scene_frame
from tests.test_world_model import write_drive
from umad_common.dataflow import Context
from umad_common.models.weights import WeightsError
from umad_common.segmentation import SEGMENTERS, build_segmenter
from umad_common.segmentation.learned import merge_small_regions
from umad_operators.segmenter import Segmenter


def train_args(data, out, *extra: str) -> argparse.Namespace:
    from umad_common.commands import train_segmenter

    parser = argparse.ArgumentParser()
    train_segmenter.add_arguments(parser)
    return parser.parse_args([str(data), "--out", str(out), *extra])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A segment net trained for one tiny epoch on three fabricated normal drives."""
    from umad_common.commands import train_segmenter

    root = tmp_path_factory.mktemp("drives")
    for i in range(3):
        write_drive(root / "normal" / f"Scenario_n{i}", frames=6, seed=i)
    write_drive(root / "anomalous" / "Scenario_a0", frames=4, seed=9, anomalous=True)  # never read
    out = root / "net.safetensors"
    flags = ("--epochs", "1", "--frames", "12", "--batch-size", "4", "--clusters", "6")
    assert train_segmenter.run(train_args(root, out, *flags)) == 0
    return root, out, flags


def test_training_writes_weights_and_a_record_and_is_deterministic(trained):
    from safetensors.torch import load_file

    from umad_common.commands import train_segmenter

    root, out, flags = trained
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["config"]["clusters"] == 6
    training = record["training"]
    assert training["command"] == shlex.join(
        ["umad", "train", "segmenter", str(root), "--out", str(out), *flags, "--threads", "1"]
    )
    assert training["heldout_drives"] == ["Scenario_n2"], "the last normal drive is held out, as for the world model"
    assert training["frames"] == 12 and training["steps"] == 3 and len(training["history"]) == 1
    assert training["seconds"] > 0 and training["history"][0]["seconds"] > 0
    again = root / "again.safetensors"
    assert train_segmenter.run(train_args(root, again, *flags)) == 0
    first, second = load_file(str(out)), load_file(str(again))
    assert all(torch.equal(first[name], second[name]) for name in first)


def test_learned_masks_tile_the_frame_and_are_deterministic(trained):
    _, out, _ = trained
    op = Segmenter({"method": "learned", "options": {"weights": str(out), "min_area": 8}})
    masks = op.process(scene_frame(0, with_truth=False))["masks"].arrays["masks"]
    assert masks.dtype == bool and masks.shape[1:] == (H, W) and masks.shape[0] >= 1
    assert (masks.sum(axis=0) == 1).all(), "every pixel in exactly one mask"
    sizes = masks.sum(axis=(1, 2))
    assert sizes.min() >= 8 or len(sizes) == 1, "small regions were merged"
    np.testing.assert_array_equal(masks, op.process(scene_frame(0, with_truth=False))["masks"].arrays["masks"])


def test_small_regions_join_their_nearest_large_region():
    regions = np.zeros((6, 8), np.int64)
    regions[:, 4:] = 1
    regions[2, 1] = 2  # a one-pixel speck inside region 0
    regions[0, 7] = 3  # and one in region 1's corner
    merged = merge_small_regions(regions, min_area=4)
    expected = np.zeros((6, 8), np.int64)
    expected[:, 4:] = 1
    np.testing.assert_array_equal(merged, expected)
    np.testing.assert_array_equal(merge_small_regions(regions, min_area=1), regions)
    np.testing.assert_array_equal(merge_small_regions(regions, min_area=1000), regions)  # no large region


def test_missing_or_broken_weights_are_refused_at_construction(tmp_path):
    with pytest.raises(WeightsError, match="missing.safetensors: segment net file not found"):
        build_segmenter("learned", {"weights": str(tmp_path / "missing.safetensors")})
    broken = tmp_path / "broken.safetensors"
    broken.write_bytes(b"not a safetensors file")
    broken.with_suffix(".json").write_text(json.dumps({"config": {"clusters": 6}}))
    with pytest.raises(WeightsError, match="broken.safetensors: cannot read safetensors file"):
        build_segmenter("learned", {"weights": str(broken)})


def test_learned_segments_any_image_size(trained):
    _, out, _ = trained
    method = build_segmenter("learned", {"weights": str(out), "min_area": 4})
    rng = np.random.default_rng(0)
    masks = method(rng.random((37, 51, 3), dtype=np.float32), scene_frame(0, with_truth=False))
    assert masks.shape[1:] == (37, 51) and (masks.sum(axis=0) == 1).all()


def test_geometry_learned_is_geometry_with_the_learned_rest(trained):
    _, out, _ = trained
    cls = SEGMENTERS["geometry_learned"]
    assert cls.Params().rest == "learned"
    assert cls.required_inputs(cls.Params()) == {"lidar"}
    problems = Segmenter.wiring_problems(Segmenter.Params(method="geometry_learned"), {"frame"})
    assert problems == ["method 'geometry_learned' needs input 'lidar' (e.g. replayer/lidar), which is not wired"]
    method = build_segmenter("geometry_learned", {"rest_options": {"weights": str(out)}, "no_lidar": "rest"}, Context())
    from umad_common.dataflow.api.messages import Message

    frame = scene_frame(0, with_truth=False)
    frame.inputs["lidar"] = Message("drive", 0, arrays={"points": np.zeros((0, 4), np.float32)})
    masks = method(frame.inputs["frame"].arrays["target"], frame)
    assert (masks.sum(axis=0) == 1).all(), "without lidar points: the learned segments alone, tiling the frame"


def test_readme_recipe_rebuilds_the_shipped_segment_net():
    """The README's `umad train segmenter` line, parsed as the CLI parses it, asks for exactly the net
    config and training config the shipped net's JSON records, and is the command it records."""
    from dataclasses import asdict

    from tests.conftest import readme_recipe
    from umad_common import ASSETS
    from umad_common.commands import train_segmenter

    args, words = readme_recipe("segmenter", train_segmenter)
    net, train = train_segmenter.configs_of(args)
    shipped = json.loads((ASSETS / "segment_net.json").read_text())
    measured = ("mean", "std")  # measured on the data while training
    recipe = json.loads(json.dumps(net.to_dict()))
    assert {k: v for k, v in recipe.items() if k not in measured} == {
        k: v for k, v in shipped["config"].items() if k not in measured
    }
    assert json.loads(json.dumps(asdict(train))) == shipped["training"]["train_config"]
    assert args.threads == shipped["training"]["threads"]
    assert shipped["training"]["command"] == train_segmenter.command_line(args) == shlex.join(words)


def test_switching_to_a_method_whose_input_is_not_wired_is_refused_with_the_reason():
    import zenoh

    from umad_common.dataflow.api.graph import validate_graph
    from umad_common.dataflow.process.control import apply_command
    from umad_common.dataflow.process.runtime import OperatorRuntime
    from umad_common.dataflow.transport.bus import zenoh_config

    graph = {
        "name": "switch",
        "operators": [
            {"id": "source", "uses": "tests.toy_ops:CounterSource"},
            {"id": "segment", "kind": "segmenter", "inputs": {"frame": "source/value"}, "params": {"method": "slic"}},
        ],
    }
    with zenoh.open(zenoh_config("peer")) as session:  # no hub, no peers
        rt = OperatorRuntime(
            graph=validate_graph(graph), op_id="segment", replica=0, session=session, shutdown=threading.Event()
        )
        outcome = apply_command(rt, json.dumps({"set": {"method": "geometry"}}).encode())
        assert outcome["status"] == "refused"
        assert "method 'geometry' needs input 'lidar' (e.g. replayer/lidar), which is not wired" in outcome["reason"]
        assert rt.operator.params.method == "slic" and rt.stats.errors == 1
        assert apply_command(rt, json.dumps({"set": {"method": "felzenszwalb"}}).encode()) == {"status": "applied"}
