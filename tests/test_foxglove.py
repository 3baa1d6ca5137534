"""The recorded log's Foxglove views: every viz message of a short run validates against the
official `@foxglove/schemas` JSON schemas (vendored, no network), and each view shows what its bus
message holds: the lidar's points at its mount, the ego's pose, the route, the masks with their
refined scores and the anomaly truth on the camera image, each map's maximum."""

from __future__ import annotations

import base64
import json
import math
from collections import Counter, defaultdict
from importlib.resources import files
from pathlib import Path

import cv2
import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader

from umad_common import DEFAULT_GRAPH, LIVE_GRAPH
from umad_common.dataflow import Frame
from umad_common.dataflow.api.graph import load_graph
from umad_common.dataflow.api.messages import Message, encode
from umad_common.dataflow.record.mcap_log import McapRecorder, read_log
from umad_common.dataflow.record.recorder import UnknownViewsError, log_views, mask_sources
from umad_common.datasets.synthetic.generator import generate_benchmark
from umad_common.datasets.synthetic.scenario import FRAME_DT, SyntheticScenario
from umad_common.refine import mask_scores, resize_nearest
from umad_common.viz.foxglove import (
    FRAME_SCORE_SCHEMA,
    SCHEMA_FOLDER,
    EgoOdometry,
    FoxgloveViews,
    score_colour,
    vendored_schemas,
)
from umad_operators.frame_result import FrameResult
from umad_operators.mask_refiner import MaskRefiner
from umad_operators.replayer import Replayer

FRAMES = 4
MAP_SHAPE = (32, 48)  # the maps' and masks' (h, w): the world model's size, smaller than the camera's
MASK_SOURCES = {"refine/refined": "segment/masks", "result/result": "segment/masks"}
VIEWS = {  # topic -> schema of every frame's views in this run
    "viz/replayer/camera": "foxglove.CompressedImage",
    "viz/replayer/lidar": "foxglove.PointCloud",
    "viz/replayer/ego/transform": "foxglove.FrameTransform",
    "viz/replayer/ego/pose": "foxglove.PoseInFrame",
    "viz/replayer/route": "foxglove.SceneUpdate",
    "viz/replayer/truth/anomaly": "foxglove.CompressedImage",
    "viz/replayer/truth/annotations": "foxglove.ImageAnnotations",
    "viz/fusion/fused": "foxglove.CompressedImage",
    "viz/fusion/fused/score": "umad.FrameScore",
    "viz/refine/refined": "foxglove.CompressedImage",
    "viz/refine/refined/score": "umad.FrameScore",
    "viz/refine/refined/masks": "foxglove.ImageAnnotations",
    "viz/result/result": "foxglove.CompressedImage",
    "viz/result/result/score": "umad.FrameScore",
}


def instance_masks(instance: np.ndarray) -> np.ndarray:
    """(K, h, w) bool: one mask per instance id (0, the background, included), at the maps' size."""
    ids = np.unique(instance)
    return resize_nearest(instance[None] == ids[:, None, None], MAP_SHAPE)


@pytest.fixture(scope="module")
def short_run(tmp_path_factory) -> tuple[Path, list, dict]:
    """A generated drive's replayer outputs, a fused map, masks, the refined map and the frame
    result of each frame through the recorder (the masks after the refined map on odd frames, as
    the bus may deliver them); the log, the replayer's frames and each frame's refined map and masks."""
    folder = tmp_path_factory.mktemp("foxglove")
    generate_benchmark(folder / "data", 0, 1, FRAMES, 5, (96, 64))
    frames = list(Replayer({"source": str(folder / "data" / "anomalous")}).frames())
    recorder = McapRecorder(folder / "run.mcap", views=FoxgloveViews, mask_sources=MASK_SOURCES)
    refined_of = {}

    def write(producer: str, output: str, frame, arrays: dict, meta: dict | None = None) -> Message:
        msg = Message(frame.run, frame.seq, frame.stamp_ns, producer, meta or {}, arrays)
        recorder.write(f"umad/toy/{producer}/{output}", encode(msg))
        return msg

    for frame in frames:
        for output, out in frame.outputs.items():
            write("replayer", output, frame, out.arrays, out.meta)
        truth = frame.outputs["truth"].arrays
        fused = resize_nearest(truth["anomaly"] == 1, MAP_SHAPE).astype(np.float32) * 0.8 + 0.1
        masks = instance_masks(truth["instance"])
        fused_msg = write("fusion", "fused", frame, {"map": fused})
        masks_msg = Message(frame.run, frame.seq, frame.stamp_ns, "segment", {}, {"masks": masks})
        joined = Frame(frame.run, frame.seq, frame.stamp_ns, {"fused": fused_msg, "masks": masks_msg})
        refined = MaskRefiner({"mode": "mean"}).process(joined)["refined"]
        if frame.seq % 2 == 0:
            recorder.write("umad/toy/segment/masks", encode(masks_msg))
        refined_msg = write("refine", "refined", frame, refined.arrays, refined.meta)
        if frame.seq % 2 == 1:
            recorder.write("umad/toy/segment/masks", encode(masks_msg))
        camera_msg = Message(frame.run, frame.seq, frame.stamp_ns, "replayer", {}, frame.outputs["camera"].arrays)
        result_frame = Frame(
            frame.run, frame.seq, frame.stamp_ns, {"refined": refined_msg, "masks": masks_msg, "camera": camera_msg}
        )
        result = FrameResult({}).process(result_frame)["result"]
        write("result", "result", frame, result.arrays, result.meta)
        refined_of[(frame.run, frame.seq)] = (refined.arrays["map"], masks)
    recorder.close()
    return folder / "run.mcap", frames, refined_of


def viz_messages(log: Path) -> list[tuple[str, str, dict, dict]]:
    """(topic, schema name, the schema stored in the log, body) of every JSON message."""
    with open(log, "rb") as f:
        return [
            (channel.topic, schema.name, json.loads(schema.data), json.loads(message.data))
            for schema, channel, message in make_reader(f).iter_messages()
            if channel.message_encoding == "json"
        ]


def by_topic(log: Path) -> dict[str, list[dict]]:
    found = defaultdict(list)
    for topic, _, _, body in viz_messages(log):
        found[topic].append(body)
    return found


def test_every_view_of_a_short_run_validates_against_the_official_foxglove_schemas(short_run):
    log, frames, _ = short_run
    messages = viz_messages(log)
    assert Counter((topic, name) for topic, name, _, _ in messages) == {item: FRAMES for item in VIEWS.items()}
    official = {name: json.loads((SCHEMA_FOLDER / f"{name}.json").read_text()) for name in vendored_schemas()}
    for topic, name, stored, body in messages:
        if name.startswith("foxglove."):
            assert stored == official[name], f"{topic}: the log's {name} is not the vendored schema"
            jsonschema.validate(body, official[name])
        else:
            assert stored == FRAME_SCORE_SCHEMA
            jsonschema.validate(body, FRAME_SCORE_SCHEMA)
    assert sum(1 for _ in read_log(log)) == FRAMES * 9  # replay reads the bus messages only


def test_the_vendored_schemas_are_the_published_package_named_in_their_readme():
    readme = (SCHEMA_FOLDER / "README.md").read_text()
    assert "`@foxglove/schemas`" in readme and "version **2.1.0**" in readme
    for name in vendored_schemas():
        schema = json.loads((SCHEMA_FOLDER / f"{name}.json").read_text())
        assert schema["title"] == name and "Generated by https://github.com/foxglove/foxglove-sdk" in schema["$comment"]
        jsonschema.validators.validator_for(schema).check_schema(schema)


def test_the_lidar_cloud_holds_the_points_in_the_ego_frame_at_the_lidar_mount(short_run):
    log, frames, _ = short_run
    clouds = by_topic(log)["viz/replayer/lidar"]
    mount = frames[0].outputs["lidar"].meta["sensors"]["lidar"]["location"]
    for frame, cloud in zip(frames, clouds, strict=True):
        points = np.frombuffer(base64.b64decode(cloud["data"]), "<f4").reshape(-1, 4)
        assert np.array_equal(points, frame.outputs["lidar"].arrays["points"])
        assert cloud["frame_id"] == "ego" and cloud["point_stride"] == 16
        position = cloud["pose"]["position"]
        assert (position["x"], position["y"], position["z"]) == (mount[0], -mount[1], mount[2])  # CARLA y is right
    assert [f["name"] for f in clouds[0]["fields"]] == ["x", "y", "z", "intensity"]


def test_each_mask_is_outlined_on_the_camera_with_its_refined_score(short_run):
    log, frames, refined_of = short_run
    annotations = by_topic(log)["viz/refine/refined/masks"]
    height, width = frames[0].outputs["camera"].arrays["rgb"].shape[:2]
    for frame, annotation in zip(frames, annotations, strict=True):
        refined, masks = refined_of[(frame.run, frame.seq)]
        scores = mask_scores(refined, masks, "mean")
        colours = {tuple(outline["outline_color"].values()) for outline in annotation["points"]}
        assert colours == {tuple(score_colour(s).values()) for s in scores[np.isfinite(scores)]}
        assert len(annotation["points"]) >= np.isfinite(scores).sum()
        xs = [p["x"] for outline in annotation["points"] for p in outline["points"]]
        ys = [p["y"] for outline in annotation["points"] for p in outline["points"]]
        assert 0 <= min(xs) and max(xs) < width and 0 <= min(ys) and max(ys) < height  # camera pixels
        top = sorted(scores[np.isfinite(scores)], reverse=True)[:5]
        assert sorted(t["text"] for t in annotation["texts"]) == sorted(f"{s:.2f}" for s in top)


def test_the_anomaly_truth_is_outlined_in_its_own_colour(short_run):
    log, frames, _ = short_run
    views = by_topic(log)
    for frame, annotation in zip(frames, views["viz/replayer/truth/annotations"], strict=True):
        anomaly = frame.outputs["truth"].arrays["anomaly"] == 1
        points = np.array([(p["x"], p["y"]) for outline in annotation["points"] for p in outline["points"]])
        if not anomaly.any():
            assert len(points) == 0
            continue
        rows, cols = np.nonzero(anomaly)
        assert (points[:, 0].min(), points[:, 0].max()) == (cols.min(), cols.max())
        assert (points[:, 1].min(), points[:, 1].max()) == (rows.min(), rows.max())
        colours = {json.dumps(o["outline_color"]) for o in annotation["points"]}
        mask_colours = {json.dumps(o["outline_color"]) for a in views["viz/refine/refined/masks"] for o in a["points"]}
        assert colours.isdisjoint(mask_colours)


def test_the_route_outline_lies_on_the_ground_around_the_ego(short_run):
    log, _, _ = short_run
    for scene in by_topic(log)["viz/replayer/route"]:
        (entity,) = scene["entities"]
        assert entity["frame_id"] == "ego" and entity["frame_locked"]
        outline = np.array([(p["x"], p["y"]) for line in entity["lines"] for p in line["points"]], np.float32)
        assert cv2.pointPolygonTest(outline.reshape(-1, 1, 2), (0.0, 0.0), False) >= 0  # the ego is on its route
        assert outline[:, 0].max() > 20  # it leads ahead


def test_each_map_s_score_is_its_maximum_and_the_frame_result_s_is_its_score(short_run):
    log, frames, refined_of = short_run
    views = by_topic(log)
    for frame, score, result in zip(
        frames, views["viz/refine/refined/score"], views["viz/result/result/score"], strict=True
    ):
        refined, _ = refined_of[(frame.run, frame.seq)]
        assert (score["run"], score["seq"]) == (frame.run, frame.seq)
        assert score["score"] == pytest.approx(float(refined.max())) == result["score"]


def test_dead_reckoning_follows_the_generated_drive():
    """The built-in world's drive from its ego actions alone: within 10 cm and a tenth of a degree
    after 10 s (84 m, a 19 degree turn; the error was under 1 cm)."""
    scenario, frames = SyntheticScenario(seed=3, frames=100), 100
    odometry = EgoOdometry()
    x0, y0, heading0 = scenario.pose(0)
    for i in range(frames):
        speed, steer = scenario.track.speed[i], scenario.track.steer[i]
        state = odometry.pose("drive", i, int(i * FRAME_DT * 1e9), float(speed), float(steer))
    x, y, heading = scenario.pose(frames - 1)
    c, s = math.cos(-heading0), math.sin(-heading0)
    truth = (c * (x - x0) - s * (y - y0), s * (x - x0) + c * (y - y0))
    driven = float(np.sum(scenario.track.speed[:-1])) * FRAME_DT
    assert driven > 80 and abs(heading - heading0) > math.radians(15)
    assert math.dist((state.x, state.y), truth) < 0.1
    assert abs(state.yaw - (heading - heading0)) < math.radians(0.1)


def test_a_frame_sent_again_keeps_its_pose_and_a_gap_moves_on_from_the_frame_before():
    odometry = EgoOdometry()
    first = odometry.pose("drive", 0, 0, 10.0, 0.0)
    second = odometry.pose("drive", 1, 100_000_000, 10.0, 0.0)
    assert (first.x, second.x) == (0.0, pytest.approx(1.0))
    assert odometry.pose("drive", 1, 100_000_000, 0.0, 1.0) == second  # re-sent: the same pose
    after_gap = odometry.pose("drive", 4, 400_000_000, 10.0, 0.0)
    assert after_gap.x == pytest.approx(4.0) and after_gap.y == 0.0
    assert odometry.pose("other", 7, 700_000_000, 10.0, 0.0).x == 0.0  # each run starts at the origin


def test_the_mask_sources_follow_the_graph_s_wiring():
    assert mask_sources(load_graph(DEFAULT_GRAPH)) == {
        "refine_gt/refined": "segment_gt/masks",
        "refine_unsup/refined": "segment_unsup/masks",
    }
    assert mask_sources(load_graph(LIVE_GRAPH)) == {"refine/refined": "segment/masks", "result/result": "segment/masks"}


def test_a_graph_s_log_holds_the_foxglove_views_unless_it_names_others():
    """The engine names the views (`record_views`), it does not import them: the recorder loads the
    class the graph names, Foxglove's by default; null records none; a bad path says what it expected."""
    graph = load_graph(DEFAULT_GRAPH)
    assert log_views(graph) is FoxgloveViews
    spec = graph.spec.model_copy(update={"record_views": None})
    assert log_views(type(graph)(spec, graph.classes, graph.path)) is None
    spec = graph.spec.model_copy(update={"record_views": "umad_common.viz.foxglove:EgoOdometry"})
    with pytest.raises(UnknownViewsError, match="expected a LogViews subclass"):
        log_views(type(graph)(spec, graph.classes, graph.path))


def test_the_shipped_layout_names_views_the_shipped_graphs_record(short_run):
    """Every topic the layout names is a view of a channel of the default or the live graph, of a
    kind this run's views have (`viz/<op>/<output>[/<view>]`)."""
    layout = json.loads((files("umad_common") / "viz" / "foxglove_layout.json").read_text())
    text = json.dumps(layout)
    named = {word.split(".")[0] for word in text.replace('"', " ").split() if word.startswith("viz/")}
    channels = {
        f"{op}/{out}"
        for graph in (DEFAULT_GRAPH, LIVE_GRAPH)
        for op, cls in load_graph(graph).classes.items()
        for out in cls.outputs
    }
    kinds = {topic.split("/", 3)[3] if topic.count("/") == 3 else "" for topic in VIEWS}
    assert named
    for topic in named:
        parts = topic.split("/")
        assert "/".join(parts[1:3]) in channels, topic
        assert "/".join(parts[3:]) in kinds, topic
    assert {"Image", "3D", "Plot"} <= {panel.split("!")[0] for panel in layout["configById"]}
