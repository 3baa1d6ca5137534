"""The shipped live graph, its per-frame result operator and its Foxglove view, `umad bench live`,
and live mode's rule: an operator takes the newest frame and passes over the ones it never got."""

import json

import numpy as np
import pytest
import yaml
from pydantic import ValidationError

from tests.conftest import run_umad
from umad_common import LIVE_GRAPH
from umad_common.dataflow import Frame
from umad_common.dataflow.api.graph import load_graph
from umad_common.dataflow.api.messages import Message
from umad_common.viz.foxglove import views
from umad_operators.frame_result import FrameResult, frame_result, mask_boxes


def test_live_graph_checks_and_is_umad_alone_at_10_hz():
    result = run_umad("graph", "check", str(LIVE_GRAPH))
    assert result.returncode == 0, result.stderr
    graph = load_graph(LIVE_GRAPH)
    kinds = {spec.kind for spec in graph.spec.operators}
    assert not kinds & {"mnad", "accumulator"}
    assert "gt" not in {spec.params.get("method") for spec in graph.spec.operators}
    assert graph.op("replayer").params | {"pacing": "realtime", "rate_hz": 10} == graph.op("replayer").params
    assert graph.sinks() == ["result"]


def two_objects() -> tuple[np.ndarray, np.ndarray]:
    """A (4, 8) refined map with two masks: mask 0 the block rows 1-2, columns 1-2 at 0.9; mask 1
    the block row 3, columns 4-7 at 0.3; mask 2 empty."""
    refined = np.zeros((4, 8), np.float32)
    masks = np.zeros((3, 4, 8), bool)
    masks[0, 1:3, 1:3] = True
    masks[1, 3, 4:8] = True
    refined[masks[0]] = 0.9
    refined[masks[1]] = 0.3
    return refined, masks


def test_mask_boxes_are_pixel_edges():
    _, masks = two_objects()
    np.testing.assert_array_equal(mask_boxes(masks[:2]), [[1, 1, 3, 3], [4, 3, 8, 4]])


def test_frame_result_orders_scales_and_leaves_out():
    refined, masks = two_objects()
    score, boxes, scores = frame_result(refined, masks, top_k=5)
    assert score == pytest.approx(0.9)
    np.testing.assert_array_equal(boxes, [[1, 1, 3, 3], [4, 3, 8, 4]])  # the empty mask is not reported
    np.testing.assert_allclose(scores, [0.9, 0.3], rtol=1e-6)
    _, boxes, scores = frame_result(refined, masks, top_k=1, image_size=(8, 32))  # 2x rows, 4x columns
    np.testing.assert_array_equal(boxes, [[4, 2, 12, 6]])
    _, boxes, _ = frame_result(refined, masks, top_k=5, min_score=0.5)
    assert boxes.shape == (1, 4)
    _, boxes, scores = frame_result(refined, masks[:0], top_k=5)
    assert boxes.shape == (0, 4) and scores.shape == (0,)


def test_frame_result_operator_on_a_frame_with_camera_and_partial_map():
    refined, masks = two_objects()
    frame = Frame(
        "drive",
        3,
        0,
        inputs={
            "refined": Message("drive", 3, meta={"partial": True}, arrays={"map": refined}),
            "masks": Message("drive", 3, arrays={"masks": masks}),
            "camera": Message("drive", 3, arrays={"rgb": np.zeros((16, 32, 3), np.uint8)}),
        },
    )
    out = FrameResult({"top_k": 2}).process(frame)["result"]
    assert out.meta == {"score": pytest.approx(0.9), "boxes": 2, "image_size": [16, 32], "partial": True}
    np.testing.assert_array_equal(out.arrays["boxes"], [[4, 4, 12, 12], [16, 12, 32, 16]])  # 4x the map
    np.testing.assert_allclose(out.arrays["box_scores"], [0.9, 0.3], rtol=1e-6)
    picture = views("result", Message("drive", 3, meta=out.meta, arrays=out.arrays))[""]
    assert picture.shape == (16, 32, 3) and picture.any()
    with pytest.raises(ValueError, match=r"expected \(h, w\) and \(K, h', w'\)"):
        flat = Message("drive", 0, arrays={"masks": refined > 0})
        FrameResult({}).process(Frame("drive", 0, 0, inputs={**frame.inputs, "masks": flat}))
    with pytest.raises(ValidationError):
        FrameResult({"top_k": -1})


def test_bench_live_counts_frames_and_times_only_those_sent_at_the_cameras_rate():
    from umad_common.benchmarks.live import Arrivals, frame_counts

    arrivals = Arrivals()
    for seq in range(6):  # frames 0-1 primed 10 ms apart, then 2-5 at 4 Hz; each result 50 ms later
        sent = 0.01 * seq if seq < 2 else 0.01 + 0.25 * (seq - 1)
        arrivals.times["camera"][("drive", seq)] = sent
        if seq != 4:
            arrivals.times["result"][("drive", seq)] = sent + 0.05
    metas = {0: {}, 1: {}, 2: {"partial": True}, 3: {}, 4: {"superseded": True}, 5: {}}
    arrivals.result_meta = {("drive", seq): meta for seq, meta in metas.items()}
    counts = frame_counts(arrivals, sent=7, primed=2)
    assert (counts["frames_kept"], counts["frames_partial"], counts["frames_superseded"]) == (4, 1, 1)
    assert counts["frames_dropped"] == 2 and counts["frames_missed"] == 3  # seq 6 never answered
    assert counts["stream_s"] == pytest.approx(0.8) and counts["fps_kept"] == pytest.approx(2 / 0.8)


@pytest.mark.slow
def test_bench_live_reports_kept_missed_latency_and_cpu_per_operator(hub_endpoint):
    from umad_common.benchmarks.live import bench_live

    result = bench_live(frames=16, hub=hub_endpoint, rate_hz=4.0)  # a slow rate: the test runs beside others
    assert result["frames_sent"] == 16 and result["frames_failed"] == 0
    counted = ("frames_kept", "frames_partial", "frames_dropped")
    assert sum(result[k] for k in counted) == 16 and result["frames_missed"] == 16 - result["frames_kept"]
    at_rate = 16 - result["frames_primed"]  # priming sends at most 3 s of frames one at a time
    assert result["frames_kept"] >= 1 and at_rate >= 2
    assert 0 < result["fps_kept"] <= 4.0 * at_rate / (at_rate - 1)  # n frames 1/rate apart span (n - 1)/rate
    for name in ("camera_to_refined", "camera_to_result"):
        latency = result["latency_ms"][name]
        assert latency["frames"] >= result["frames_kept"]
        assert 0 < latency["p50"] <= latency["p99"] <= latency["max"]
    assert result["latency_ms"]["camera_to_refined"]["p50"] <= result["latency_ms"]["camera_to_result"]["p50"]
    operators = result["cpu_ms_per_frame"]
    assert {"replayer", "world_model", "fusion", "segment", "refine", "result"} <= set(operators)
    assert "mnad" not in operators and operators["world_model"]["cpu_ms"] > 0


def launch_chain(tmp_path, name: str, hub: str, source: dict, operator: dict):
    """Launch the live toy graph `source` -> `operator` (id, uses, inputs, params) -> a sink that logs
    every frame it gets to sink.jsonl; the launcher's result."""
    graph = {
        "name": name,
        "hub": hub,
        "operators": [
            {"id": "source", **source},
            operator,
            {
                "id": "sink",
                "uses": "tests.toy_ops:Logger",
                "inputs": {"x": f"{operator['id']}/y"},
                "params": {"log": str(tmp_path / "sink.jsonl")},
            },
        ],
    }
    path = tmp_path / "graph.yaml"
    path.write_text(yaml.safe_dump(graph, sort_keys=False))
    result = run_umad("launch", str(path), timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    return result


def logged_seqs(path) -> list[int]:
    return [json.loads(line)["seq"] for line in path.read_text().splitlines()]


@pytest.mark.slow
def test_a_slow_ordered_operator_in_live_mode_passes_over_lost_and_stale_frames_and_never_stalls(
    tmp_path, hub_endpoint
):
    """A realtime source at 20 Hz, an ordered operator that needs 0.15 s a frame and never gets
    frame 5 whole (its `extra` payload is lost), and a sink. Waiting in order, the operator stalled
    at frame 5 for the rest of the run; working through its backlog, its latency would grow with
    the run. Now it processes the newest frame it has, the rest are passed over and counted, the
    sink acks the passed-over frames' markers, and the run's last frame reaches the sink."""
    frames = 80
    source = {
        "uses": "tests.toy_ops:LossyPairSource",
        "params": {"frames": frames, "pacing": "realtime", "rate_hz": 20, "lose_extra": [5], "ack_timeout_s": 60},
    }
    ordered = {
        "id": "ordered",
        "uses": "tests.toy_ops:SlowOrdered",
        "inputs": {"x": "source/value", "extra": "source/extra"},
        "params": {"delay_s": 0.15, "log": str(tmp_path / "ordered.jsonl")},
    }
    result = launch_chain(tmp_path, "toy_live", hub_endpoint, source, ordered)
    processed, reached = logged_seqs(tmp_path / "ordered.jsonl"), logged_seqs(tmp_path / "sink.jsonl")
    assert processed == sorted(set(processed)) and 5 not in processed  # in order, the lost frame passed over
    assert processed[-1] == frames - 1 and reached[-1] == frames - 1  # the stream went on to the run's end
    assert set(reached) <= set(processed) and len(processed) < frames - 1  # stale frames passed over too
    lines = result.stdout.splitlines()
    header = next(line for line in lines if line.endswith("(times: ms per frame)")).split()
    ordered_stats = next(line for line in lines if line.startswith("ordered.r0")).split()
    passed = int(ordered_stats[header.index("passed")])
    assert passed >= 1 and len(processed) + passed == frames  # every frame processed or counted
    assert "given up" not in result.stdout  # the sink acked every frame, passed-over ones by their markers


@pytest.mark.slow
def test_a_live_source_starts_its_clock_once_the_graph_has_taken_its_first_frame(tmp_path, hub_endpoint):
    """An operator whose first frame costs 1.5 s (start-up) and later ones 40 ms, at 10 Hz: had the
    camera gone on meanwhile, the backlog would have had frames passed over. The source waits for
    the first frame's ack before its clock starts, so every frame is processed."""
    frames = 40
    source = {"uses": "tests.toy_ops:CounterSource", "params": {"frames": frames, "pacing": "realtime", "rate_hz": 10}}
    scale = {
        "id": "scale",
        "uses": "tests.toy_ops:Scale",
        "inputs": {"x": "source/value"},
        "params": {"delay_s": 0.04, "first_delay_s": 1.5},
    }
    launch_chain(tmp_path, "toy_priming", hub_endpoint, source, scale)
    assert logged_seqs(tmp_path / "sink.jsonl") == list(range(frames))
