"""The runtime with real processes on a real Zenoh hub on loopback, started as a user would."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from collections import Counter
from pathlib import Path

import pytest
import yaml
import zenoh

from tests.conftest import DrainedUmad, run_umad, start_umad
from umad_common.dataflow.api.messages import decode
from umad_common.dataflow.record.mcap_log import LogError, read_log
from umad_common.dataflow.transport.bus import open_client

pytestmark = pytest.mark.slow


def toy_graph(tmp_path: Path, hub: str, frames=30, delay=0.0, replicas=2, window=4) -> Path:
    data = {
        "name": "toy",
        "hub": hub,
        "operators": [
            {
                "id": "source",
                "uses": "tests.toy_ops:CounterSource",
                "params": {"frames": frames, "runs": 2, "window": window},
            },
            {
                "id": "double",
                "uses": "tests.toy_ops:Scale",
                "inputs": {"x": "source/value"},
                "replicas": replicas,
                "params": {"delay_s": delay},
            },
            {"id": "triple", "uses": "tests.toy_ops:Scale", "inputs": {"x": "source/value"}, "params": {"factor": 3}},
            {
                "id": "sink",
                "uses": "tests.toy_ops:JoinSink",
                "inputs": {"a": "source/value", "b": "*le/y"},
                "params": {"log": str(tmp_path / "sink.jsonl")},
            },
        ],
    }
    path = tmp_path / "graph.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def sink_lines(tmp_path: Path) -> list[dict]:
    return [json.loads(line) for line in (tmp_path / "sink.jsonl").read_text().splitlines()]


def assert_exactly_once(tmp_path: Path, frames: int) -> None:
    lines = sink_lines(tmp_path)
    seen = Counter((x["run"], x["seq"]) for x in lines if "seq" in x)
    assert sorted(seen) == [(f"run{r}", s) for r in range(2) for s in range(frames)]
    assert set(seen.values()) == {1}, [k for k, v in seen.items() if v > 1]
    for x in lines:
        if "seq" in x:
            base = x["seq"] + 1000 * int(x["run"][3:])
            assert x["total"] == base * 6 and x["producers"] == ["double", "triple"]
    assert [x["run"] for x in lines if x.get("end")] == ["run0", "run1"]


def zenoh_segments() -> set[str]:
    return {p.name for p in Path("/dev/shm").glob("*.zenoh")} if Path("/dev/shm").is_dir() else set()


def watch_stats(session, *wait_for: str) -> tuple[dict[str, dict], object]:
    """Collect the toy graph's stats by key; returns once each of `wait_for` has reported (it is
    subscribed to its inputs then)."""
    stats: dict[str, dict] = {}
    sub = session.declare_subscriber(
        "umad/toy/_stats/**", lambda s: stats.update({str(s.key_expr): json.loads(s.payload.to_bytes())})
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not all(f"umad/toy/_stats/{op}/r0" in stats for op in wait_for):
        time.sleep(0.1)
    return stats, sub


def test_toy_graph_delivers_every_frame_exactly_once(tmp_path, hub_endpoint):
    before = zenoh_segments()
    result = run_umad("launch", str(toy_graph(tmp_path, hub_endpoint)), timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert_exactly_once(tmp_path, 30)
    assert "[double.0]" in result.stdout and "[sink.0]" in result.stdout  # log lines carry the replica id
    assert zenoh_segments() <= before
    table = result.stdout[result.stdout.index("(times: ms per frame)") :].splitlines()
    sink = next(line for line in table if line.startswith("sink.r0")).split()
    assert "-" not in sink  # where the sink's time went: CPU, runtime, join wait, queue, transport


def test_a_graph_whose_hub_endpoint_is_taken_refuses_to_start(tmp_path, hub_endpoint):
    """Another hub on the endpoint (a graph that did not stop): our hub could not listen there and our
    replicas would join that graph's hub, mixing frames of two graphs. `umad launch` says so before it
    starts anything (the launcher's own check, which asks the bus, stays behind it)."""
    from umad_common.dataflow.transport.bus import open_hub

    other = open_hub(hub_endpoint)
    try:
        result = run_umad("launch", str(toy_graph(tmp_path, hub_endpoint)), timeout=60)
    finally:
        other.close()
    assert result.returncode == 2
    port = hub_endpoint.rsplit(":", 1)[1]
    assert f"hub {hub_endpoint}: port {port} is in use" in result.stderr
    assert not (tmp_path / "sink.jsonl").exists()  # no replica was started


def test_messages_larger_than_the_graphs_shared_memory_pool_arrive_exactly_once(tmp_path, hub_endpoint):
    path = toy_graph(tmp_path, hub_endpoint, frames=10)
    data = yaml.safe_load(path.read_text())
    data["shm_pool_mib"] = 1
    data["operators"][0]["params"]["size"] = 600_000  # 2.4 MB per message: never fits, takes the hub's socket
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    result = run_umad("launch", str(path), timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert_exactly_once(tmp_path, 10)


def pid_once_sinking(tmp_path, pattern: str, wait_s: float = 60) -> int | None:
    """The pid of the process whose command line matches `pattern`, once the sink has written more
    than 10 lines (None if that does not happen within `wait_s`)."""
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        out = subprocess.run(["pgrep", "-f", "--", pattern], capture_output=True, text=True)
        if out.stdout.strip() and (tmp_path / "sink.jsonl").exists() and len(sink_lines(tmp_path)) > 10:
            return int(out.stdout.split()[0])
        time.sleep(0.05)
    return None


def survives_sigkill(proc, pid: int, launcher_says: str, tmp_path, timeout: float) -> None:
    """SIGKILL `pid`; the launched graph still finishes cleanly, its launcher says `launcher_says`,
    and the sink saw every frame exactly once."""
    os.kill(pid, signal.SIGKILL)
    out, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, out
    assert launcher_says in out
    assert_exactly_once(tmp_path, 60)


def test_sigkill_of_a_replica_loses_and_duplicates_nothing(tmp_path, hub_endpoint):
    graph = toy_graph(tmp_path, hub_endpoint, frames=60, delay=0.03)
    proc = start_umad("launch", str(graph))
    victim = pid_once_sinking(tmp_path, f"--graph {graph} --op double --replica 1")
    assert victim, "replica never started"
    survives_sigkill(proc, victim, "restart 1/3", tmp_path, timeout=180)


def test_malformed_payloads_are_counted_and_the_operator_goes_on(tmp_path, hub_endpoint):
    graph = toy_graph(tmp_path, hub_endpoint, frames=40, delay=0.05, replicas=1)
    proc = start_umad("launch", str(graph))
    session = open_client(hub_endpoint)
    try:
        stats, sub = watch_stats(session, "triple", "sink")
        pub = session.declare_publisher("umad/toy/source/value", congestion_control=zenoh.CongestionControl.BLOCK)
        for payload in (b"garbage", b"\x80", b"\x81\xa1v\x07"):
            pub.put(payload)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not all(
            stats.get(f"umad/toy/_stats/{op}/r0", {}).get("bad_messages", 0) >= 3 for op in ("triple", "sink")
        ):
            time.sleep(0.1)
        assert stats["umad/toy/_stats/triple/r0"]["bad_messages"] == 3
        assert stats["umad/toy/_stats/sink/r0"]["bad_messages"] == 3
        sub.undeclare()
    finally:
        session.close()
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, out
    assert_exactly_once(tmp_path, 40)


def test_bad_control_commands_are_rejected_and_the_operator_goes_on(tmp_path, hub_endpoint):
    frames = 300  # long enough for three commands on a busy machine
    graph = toy_graph(tmp_path, hub_endpoint, frames=frames, delay=0.05, replicas=1)
    proc = start_umad("launch", str(graph))
    session = open_client(hub_endpoint)
    try:
        stats, sub = watch_stats(session, "triple")
        bad = (b"not json", b"[1]", b'{"set": 5}', b'{"set": {"factor": "big"}}', b'{"set": {"nope": 1}}')
        for payload in bad:  # straight to the replica's command key, each answered
            replies = session.get("umad/toy/_ctl/triple", payload=payload, timeout=30)
            answers = [json.loads(reply.ok.payload.to_bytes()) for reply in replies if reply.ok is not None]
            assert [answer["status"] for answer in answers] == ["refused"], (payload, answers)
        # Commands find the graph on the hub (no --graph) and hear back what each replica did.
        refused = run_umad("set", "triple.factor=big", "--connect", hub_endpoint)
        assert refused.returncode == 1, refused.stdout + refused.stderr
        assert "triple.r0: refused: factor: Input should be a valid number" in refused.stderr
        declined = run_umad("set", "triple.factor=0", "--connect", hub_endpoint)
        assert (
            declined.returncode == 1 and "triple.r0: refused: ValueError: a factor of 0 is refused" in declined.stderr
        )
        unknown = run_umad("set", "nope.factor=2", "--connect", hub_endpoint)
        assert unknown.returncode == 1 and "nope: no such operator in the running graph 'toy'" in unknown.stderr
        stopped = run_umad("op", "stop", "no_such_op", "--connect", hub_endpoint)
        assert stopped.returncode == 1 and "no_such_op: refused: no_such_op is not running" in stopped.stderr
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and stats["umad/toy/_stats/triple/r0"]["errors"] < len(bad) + 2:
            time.sleep(0.1)
        assert stats["umad/toy/_stats/triple/r0"]["errors"] == len(bad) + 2  # the two refused `umad set` too
        assert stats["umad/toy/_stats/triple/r0"]["param_changes"] == 0
        sub.undeclare()
    finally:
        session.close()
    out, _ = proc.communicate(timeout=180)
    assert proc.returncode == 0, out
    assert out.count("rejected parameter change") == len(bad) + 1
    assert_exactly_once(tmp_path, frames)  # the old parameters stayed: every total is still x6


def test_set_without_a_running_graph_says_so(tmp_path, hub_endpoint):
    result = run_umad("set", "triple.factor=4", "--graph", str(toy_graph(tmp_path, hub_endpoint)), timeout=60)
    assert result.returncode == 1
    assert f"no hub at {hub_endpoint}" in result.stderr


def test_frame_that_raises_is_logged_counted_and_the_stream_goes_on(tmp_path, hub_endpoint):
    graph = toy_graph(tmp_path, hub_endpoint, frames=10, replicas=1)
    result = run_umad("launch", str(graph), "--set", "double.fail_on_seq=3", timeout=120)
    assert result.returncode == 0, result.stdout
    assert "frame run0#3 failed: asked to fail" in result.stdout
    seqs = {(x["run"], x["seq"]) for x in sink_lines(tmp_path) if "seq" in x}
    assert ("run0", 3) not in seqs and len(seqs) == 18


def test_record_then_replay_gives_byte_identical_sink_outputs(tmp_path, hub_endpoint):
    graph = toy_graph(tmp_path, hub_endpoint, frames=15)
    first, second = tmp_path / "first.mcap", tmp_path / "second.mcap"
    result = run_umad("launch", str(graph), "--record", str(first), timeout=120)
    assert result.returncode == 0, result.stdout
    result = run_umad("replay", str(first), "--graph", str(graph), "--record", str(second), timeout=120)
    assert result.returncode == 0, result.stdout

    def sink_payloads(path):
        out = {}
        for rec in read_log(path):
            if rec.topic == "umad/toy/sink/total":
                msg = decode(rec.data)
                out.setdefault((msg.run, msg.seq), rec.data)
        return out

    a, b = sink_payloads(first), sink_payloads(second)
    assert len(a) == 2 * 16 and a == b


def replayer_graph(tmp_path: Path, name: str, hub: str) -> Path:
    """The real replayer on tmp_path/data/anomalous feeding a light sink of camera statistics."""
    graph = tmp_path / "graph.yaml"
    source = str(tmp_path / "data" / "anomalous")
    operators = [
        {"id": "replayer", "kind": "replayer", "params": {"source": source}},
        {"id": "stats", "uses": "tests.toy_ops:ImageStats", "inputs": {"image": "replayer/camera"}},
    ]
    graph.write_text(yaml.safe_dump({"name": name, "hub": hub, "operators": operators}, sort_keys=False))
    return graph


def test_replay_needs_only_the_log_and_keeps_the_recorded_overrides(tmp_path, hub_endpoint):
    """The data folder is gone and no --graph is given: the log's graph, its --set overrides and its
    source frames reproduce the sink's outputs byte for byte."""
    from umad_common.datasets.synthetic.generator import generate_benchmark

    generate_benchmark(tmp_path / "data", 0, 1, 6, 5, (96, 64))
    graph = replayer_graph(tmp_path, "logonly", hub_endpoint)
    first, second = tmp_path / "first.mcap", tmp_path / "second.mcap"
    result = run_umad("launch", str(graph), "--record", str(first), "--set", "stats.scale=2", timeout=120)
    assert result.returncode == 0, result.stdout
    shutil.rmtree(tmp_path / "data")
    graph.unlink()
    result = run_umad("replay", str(first), "--record", str(second), timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr

    def stats_payloads(path):
        return {decode(r.data).seq: r.data for r in read_log(path) if r.topic == "umad/logonly/stats/stats"}

    a, b = stats_payloads(first), stats_payloads(second)
    assert len(a) == 7 and a == b  # six frames and the end-of-run marker
    assert all(decode(a[seq]).meta["params"] == {"scale": 2.0} for seq in range(6))
    assert_foxglove_views(first, frames=6, shape=(64, 96, 3))


def test_a_frame_with_a_missing_file_travels_as_an_error_and_the_stream_goes_on(tmp_path, hub_endpoint):
    from umad_common.datasets.synthetic.generator import generate_benchmark

    generate_benchmark(tmp_path / "data", 0, 2, 6, 5, (96, 64))
    scenario = sorted((tmp_path / "data" / "anomalous").glob("Scenario_*"))[1]
    semantic = sorted(next(scenario.glob("SEMANTIC-CAM*")).iterdir())[3]
    semantic.unlink()
    graph = replayer_graph(tmp_path, "missing", hub_endpoint)
    result = run_umad("launch", str(graph), "--record", str(tmp_path / "run.mcap"), timeout=120)
    assert result.returncode == 0, result.stdout
    assert f"{scenario.name}#3 cannot be read" in result.stdout and semantic.name.split("_")[-1][:-4] in result.stdout
    assert "restart" not in result.stdout  # a data error is not a crash
    outputs = [decode(r.data) for r in read_log(tmp_path / "run.mcap") if r.topic == "umad/missing/stats/stats"]
    frames = [m for m in outputs if not m.meta.get("eos")]
    assert len(frames) == 12
    failed = [(m.run, m.seq) for m in frames if m.meta.get("error")]
    assert failed == [(scenario.name, 3)]  # the other 11 frames were computed as usual
    assert all("x" in m.arrays for m in frames if not m.meta.get("error"))


def assert_foxglove_views(log: Path, frames: int, shape: tuple[int, int, int]) -> None:
    """The log opens in Foxglove: every replayer view is there for every frame, each a JSON message
    that validates against the vendored official schema; the camera is a JPEG of the camera's size."""
    import base64

    import cv2
    import jsonschema
    import numpy as np
    from mcap.reader import make_reader

    from umad_common.viz.foxglove import schema as foxglove_schema

    with open(log, "rb") as f:
        views = [
            (channel.topic, schema.name, channel.message_encoding, json.loads(message.data))
            for schema, channel, message in make_reader(f).iter_messages()
            if channel.topic.startswith("viz/")
        ]
    assert Counter((topic, name, encoding) for topic, name, encoding, _ in views) == {
        (topic, name, "json"): frames
        for topic, name in [
            ("viz/replayer/camera", "foxglove.CompressedImage"),
            ("viz/replayer/lidar", "foxglove.PointCloud"),
            ("viz/replayer/ego/transform", "foxglove.FrameTransform"),
            ("viz/replayer/ego/pose", "foxglove.PoseInFrame"),
            ("viz/replayer/route", "foxglove.SceneUpdate"),
            ("viz/replayer/truth/anomaly", "foxglove.CompressedImage"),
            ("viz/replayer/truth/annotations", "foxglove.ImageAnnotations"),
        ]
    }
    for _, name, _, body in views:
        jsonschema.validate(body, foxglove_schema(name))
    camera = next(body for topic, _, _, body in views if topic == "viz/replayer/camera")
    picture = cv2.imdecode(np.frombuffer(base64.b64decode(camera["data"]), np.uint8), cv2.IMREAD_COLOR)
    assert camera["format"] == "jpeg" and picture.shape == shape


def test_truncated_log_says_how_many_messages_were_readable(tmp_path, hub_endpoint):
    graph = toy_graph(tmp_path, hub_endpoint, frames=15)
    log = tmp_path / "rec.mcap"
    assert run_umad("launch", str(graph), "--record", str(log), timeout=120).returncode == 0
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(LogError, match=r"after \d+ readable messages") as info:
        list(read_log(cut))
    assert len(list(read_log(cut, allow_truncated=True))) == info.value.readable
    result = run_umad("replay", str(cut), "--graph", str(graph))
    assert result.returncode != 0 and "readable messages" in result.stderr and "--allow-truncated" in result.stderr


def test_ctrl_c_stops_everything_and_leaves_no_process_or_segment(tmp_path, hub_endpoint):
    before = zenoh_segments()
    graph = toy_graph(tmp_path, hub_endpoint, frames=1000, delay=0.05)
    launch = DrainedUmad("launch", str(graph))
    deadline = time.monotonic() + 60
    while not ((tmp_path / "sink.jsonl").exists() and sink_lines(tmp_path)) and time.monotonic() < deadline:
        time.sleep(0.1)
    launch.proc.send_signal(signal.SIGINT)
    launch.wait(timeout=60)
    assert launch.proc.returncode == 130
    left = subprocess.run(["pgrep", "-f", "--", f"--graph {graph}"], capture_output=True, text=True).stdout
    assert left.strip() == ""
    assert zenoh_segments() <= before


def test_a_stopping_graph_signals_consumers_before_their_producers(tmp_path, hub_endpoint):
    """A producer that leaves first would let a consumer complete a frame in flight without its
    output (what a producer stopped by `umad op stop` means); consumers must stop first."""
    from umad_common.dataflow.api.graph import load_graph
    from umad_common.dataflow.launch.launcher import Launcher

    graph = toy_graph(tmp_path, hub_endpoint)
    launcher = Launcher(load_graph(graph), graph, quiet=True)
    signalled = []

    class Running:
        def __init__(self, op_id: str):
            self.op_id = op_id

        def poll(self):
            return None

        def send_signal(self, sig):
            signalled.append((self.op_id, sig))

    for rep in launcher.replicas:
        rep.proc = Running(rep.op_id)
    launcher._signal_all(signal.SIGTERM)
    order = [op_id for op_id, _ in signalled]
    assert order[0] == "sink" and order[-1] == "source" and sorted(order[1:-1]) == ["double", "double", "triple"]
    assert {sig for _, sig in signalled} == {signal.SIGTERM}


def test_operator_that_cannot_start_fails_the_graph_without_restarts(tmp_path, hub_endpoint):
    graph = toy_graph(tmp_path, hub_endpoint)
    data = yaml.safe_load(graph.read_text())
    data["operators"][1]["params"]["delay_s"] = 0.0
    data["operators"][1]["uses"] = "tests.toy_ops:Scale"
    graph.write_text(yaml.safe_dump(data))
    result = run_umad("launch", str(graph), "--set", "double.factor=oops", timeout=60)
    assert result.returncode != 0
    assert "parameter 'factor'" in result.stderr


def test_hub_restart_is_survived_by_reconnecting_clients(tmp_path, hub_endpoint):
    graph = toy_graph(tmp_path, hub_endpoint, frames=60, delay=0.03)
    proc = start_umad("launch", str(graph))
    hub_pid = pid_once_sinking(tmp_path, f"umad_common.dataflow.transport.hub --listen {hub_endpoint}")
    assert hub_pid
    survives_sigkill(proc, hub_pid, "[hub] exited with -9; restarting", tmp_path, timeout=240)


def test_hot_swap_start_stop_and_set_take_effect_on_later_frames(tmp_path, hub_endpoint):
    graph = toy_graph(tmp_path, hub_endpoint, frames=2000, delay=0.02, replicas=1)  # stopped with SIGINT below
    data = yaml.safe_load(graph.read_text())
    data["operators"][0]["params"]["runs"] = 1
    graph.write_text(yaml.safe_dump(data, sort_keys=False))
    proc = start_umad("launch", str(graph), "--record", str(tmp_path / "run.mcap"))

    def wait_for(predicate, what):
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if (tmp_path / "sink.jsonl").exists() and predicate(sink_lines(tmp_path)):
                return
            time.sleep(0.1)
        raise AssertionError(f"timed out waiting for {what}")

    wait_for(lambda lines: len(lines) > 20, "first frames")
    data["operators"].insert(
        3, {"id": "quadruple", "uses": "tests.toy_ops:Scale", "inputs": {"x": "source/value"}, "params": {"factor": 4}}
    )
    graph.write_text(yaml.safe_dump(data, sort_keys=False))
    assert run_umad("op", "start", "quadruple", "--graph", str(graph)).returncode == 0
    wait_for(lambda lines: any("quadruple" in x.get("producers", []) for x in lines), "quadruple to join")
    changed = run_umad("set", "double.factor=5", "--connect", hub_endpoint)
    assert changed.returncode == 0 and "double.r0: applied: {'factor': 5}" in changed.stdout, changed.stderr
    wait_for(lambda lines: any(x.get("total") == x["seq"] * 13 and x["seq"] for x in lines if "seq" in x), "factor 5")
    stopped = run_umad("op", "stop", "quadruple", "--connect", hub_endpoint)
    assert stopped.returncode == 0 and "quadruple: applied: stopping quadruple (1 replicas)" in stopped.stdout
    n_before_stop = len(sink_lines(tmp_path))
    wait_for(
        lambda lines: len(lines) > n_before_stop + 20 and lines[-1]["producers"] == ["double", "triple"],
        "quadruple to leave",
    )
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=60)

    lines = [x for x in sink_lines(tmp_path) if "seq" in x]
    totals = {x["seq"]: (x["total"] / x["seq"], tuple(x["producers"])) for x in lines if x["seq"]}
    seen = [totals[s] for s in sorted(totals)]
    # Every frame used one consistent set of maps and parameters; the changes appear in this order.
    assert seen[0] == (6.0, ("double", "triple"))
    assert (10.0, ("double", "quadruple", "triple")) in seen
    assert (13.0, ("double", "quadruple", "triple")) in seen
    assert seen[-1] == (9.0, ("double", "triple"))
    order = [
        seen.index(x) for x in [(10.0, ("double", "quadruple", "triple")), (13.0, ("double", "quadruple", "triple"))]
    ]
    assert order == sorted(order)
    assert "parameters changed: {'factor': 5}" in out
    # The log says what changed and when: the control messages are recorded with the frames.
    from mcap.reader import make_reader

    with open(tmp_path / "run.mcap", "rb") as f:
        control = [
            (channel.topic, json.loads(message.data))
            for _, channel, message in make_reader(f).iter_messages()
            if "/_ctl/" in channel.topic
        ]
    assert ("umad/toy/_ctl/double", {"set": {"factor": 5}}) in control
    assert [c[1].get("start") or c[1].get("stop") for c in control if c[0] == "umad/toy/_ctl/_launcher"] == [
        "quadruple",
        "quadruple",
    ]


def test_restarted_stateful_operator_rebuilds_its_state_and_results_match(tmp_path, hub_endpoint):
    frames = 60
    data = {
        "name": "stateful",
        "hub": hub_endpoint,
        "operators": [
            {
                "id": "source",
                "uses": "tests.toy_ops:RewindableCounterSource",
                "params": {"frames": frames, "runs": 2, "window": 4, "ack_timeout_s": 2.0},
            },
            {
                "id": "cumsum",
                "uses": "tests.toy_ops:RunningSum",
                "inputs": {"x": "source/value"},
                "params": {"delay_s": 0.03},
            },
            {
                "id": "log",
                "uses": "tests.toy_ops:Logger",
                "inputs": {"x": "cumsum/y"},
                "params": {"log": str(tmp_path / "log.jsonl")},
            },
        ],
    }
    graph = tmp_path / "graph.yaml"
    graph.write_text(yaml.safe_dump(data, sort_keys=False))
    proc = start_umad("launch", str(graph))
    log = tmp_path / "log.jsonl"
    deadline = time.monotonic() + 60
    victim = None
    while victim is None and time.monotonic() < deadline:
        out = subprocess.run(["pgrep", "-f", "--", f"--graph {graph} --op cumsum"], capture_output=True, text=True)
        if out.stdout.strip() and log.exists() and len(log.read_text().splitlines()) > 15:
            victim = int(out.stdout.split()[0])
        time.sleep(0.05)
    assert victim
    os.kill(victim, signal.SIGKILL)
    out, _ = proc.communicate(timeout=180)
    assert proc.returncode == 0, out
    assert "asking the sources to resend them" in out and "resent run0#0.." in out
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    values = {(x["run"], x["seq"]): x["value"] for x in lines}
    expected = {(f"run{r}", s): float(sum(v + 1000 * r for v in range(s + 1))) for r in range(2) for s in range(frames)}
    assert values == expected  # every frame once, each with the state a fault-free run gives
    assert len(lines) == len(values)
