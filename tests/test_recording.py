"""A recorded run never loses a message, and a stop stops: the default graph recorded under CPU hogs
that outrank it, SIGTERM under the same load, and what the recorder says when a payload is lost."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

import msgpack
import numpy as np
import pytest
import yaml

from tests.conftest import REPO, UMAD, free_port, umad_env
from tests.test_runtime_e2e import toy_graph
from umad_common.dataflow.api.exit_codes import EXIT_INCOMPLETE
from umad_common.dataflow.api.graph import load_graph
from umad_common.dataflow.api.messages import Message, decode, encode
from umad_common.dataflow.record.mcap_log import describe_loss, read_log, read_metadata, recording_outcome
from umad_common.dataflow.record.recorder import Recording
from umad_common.dataflow.transport.bus import RECORDER, Keys, open_client, open_hub
from umad_common.dataflow.transport.planes.ring import PayloadRing

FRAMES = 60  # per drive: at 60 a recorder without flow control lost 55 of 122 camera frames this way
NICE = 10  # the graph's priority below the hogs'


@pytest.fixture(scope="module")
def two_drives(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("drives")
    subprocess.run(
        [*UMAD, "generate", "synthetic", str(folder), "--normal", "0", "--anomalous", "2", "--frames", str(FRAMES)]
        + ["--seed", "41"],
        check=True,
        capture_output=True,
        env=umad_env(),
        cwd=REPO,
    )
    return folder / "anomalous"


class CpuHogs:
    """A busy loop on every core, at the default priority (the graph runs below it)."""

    def __enter__(self) -> CpuHogs:
        loop = "while True: pass"
        self.procs = [subprocess.Popen([sys.executable, "-c", loop]) for _ in range(os.cpu_count() or 1)]
        return self

    def __exit__(self, *exc) -> None:
        for proc in self.procs:
            proc.kill()
            proc.wait()


def launch_under_load(tmp_path: Path, drives: Path) -> tuple[subprocess.Popen, Path, Path]:
    graph = yaml.safe_load((REPO / "graph.yaml").read_text())
    graph.update(hub=f"tcp/127.0.0.1:{free_port()}", base_dir=str(REPO))
    for op in graph["operators"]:
        if op["kind"] == "replayer":
            op["params"]["source"] = str(drives)
    graph_file, log = tmp_path / "graph.yaml", tmp_path / "run.mcap"
    graph_file.write_text(yaml.safe_dump(graph, sort_keys=False))
    out = open(tmp_path / "launch.out", "w")
    proc = subprocess.Popen(
        ["nice", "-n", str(NICE), *UMAD, "launch", str(graph_file), "--record", str(log)],
        stdout=out,
        stderr=subprocess.STDOUT,
        env=umad_env(),
        cwd=REPO,
    )
    return proc, graph_file, log


def frames_by_channel(log: Path) -> dict[str, set[tuple[str, int]]]:
    frames: dict[str, set[tuple[str, int]]] = defaultdict(set)
    for m in read_log(log):
        msg = decode(m.data)
        frames[m.topic].add((msg.run, msg.seq))
    return frames


@pytest.mark.slow
def test_the_default_graph_recorded_under_cpu_hogs_holds_every_frame_on_every_channel(tmp_path, two_drives):
    with CpuHogs():
        proc, graph_file, log = launch_under_load(tmp_path, two_drives)
        code = proc.wait(timeout=900)
    output = (tmp_path / "launch.out").read_text()
    assert code == 0, output[-4000:]
    frames = frames_by_channel(log)
    graph = load_graph(graph_file)
    channels = {f"umad/umad/{op}/{out}" for op, cls in graph.classes.items() for out in cls.outputs}
    assert set(frames) == channels
    wanted = {(run.name, seq) for run in two_drives.iterdir() for seq in range(FRAMES + 1)}  # + end-of-run
    lacking = {channel: len(wanted - got) for channel, got in frames.items() if wanted - got}
    assert not lacking, lacking
    assert recording_outcome(log) == {"lost": {}, "lacking": {}, "stopped": False}
    assert "could not be read" not in output


@pytest.mark.slow
def test_sigterm_under_cpu_hogs_stops_within_5_s_and_leaves_a_readable_log(tmp_path, two_drives):
    with CpuHogs():
        proc, graph_file, log = launch_under_load(tmp_path, two_drives)
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline and proc.poll() is None:
            if "frames through the graph" in (tmp_path / "launch.out").read_text():
                break
            time.sleep(0.5)
        assert proc.poll() is None, (tmp_path / "launch.out").read_text()[-4000:]
        proc.send_signal(signal.SIGTERM)
        signalled = time.monotonic()
        code = proc.wait(timeout=60)
        took = time.monotonic() - signalled
    output = (tmp_path / "launch.out").read_text()
    assert code == 130, output[-4000:]
    assert took <= 5.0, f"took {took:.1f} s to stop\n{output[-4000:]}"
    left = subprocess.run(["pgrep", "-f", "--", f"--graph {graph_file}"], capture_output=True, text=True).stdout
    assert left.strip() == ""
    assert sum(1 for _ in read_log(log)) > 0  # readable to its end: no LogError
    assert recording_outcome(log)["stopped"] is True
    assert "world_model" in read_metadata(log)["graph"]


def test_a_payload_the_recorder_cannot_read_is_counted_and_the_log_says_so(tmp_path, hub_endpoint):
    graph = load_graph(toy_graph(tmp_path, hub_endpoint))
    keys = Keys(graph.name)
    hub = open_hub(hub_endpoint)
    publisher, launcher = open_client(hub_endpoint), open_client(hub_endpoint)
    try:
        acks: list[dict] = []
        ack_sub = publisher.declare_subscriber(
            keys.ack_all, lambda s: acks.append(msgpack.unpackb(s.payload.to_bytes()))
        )
        recording = Recording(launcher, graph, tmp_path / "run.mcap", {"graph": "name: toy", "base_dir": "."})
        ring = PayloadRing(
            keys.payload("source"), tmp_path / "elsewhere"
        )  # a ring the recorder cannot map, nobody serves
        (tmp_path / "elsewhere").mkdir()
        camera = encode(Message("run0", 0, 0, "source", {}, {"x": np.zeros(1 << 17, np.uint8)}))
        publisher.put(keys.data("source", "value"), ring.pack(camera))
        publisher.put(keys.data("source", "value"), encode(Message("run0", 1, 0, "source", {}, {})))
        for op, port in (("double", "y"), ("triple", "y"), ("sink", "total")):
            for seq in (0, 1):
                publisher.put(keys.data(op, port), encode(Message("run0", seq, 0, op, {}, {})))
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not any(a["seq"] == 1 for a in acks if a["op"] == RECORDER):
            time.sleep(0.05)
        assert {"run": "run0", "seq": 1, "op": RECORDER} in acks  # every channel of frame 1 written
        assert not any(a["seq"] == 0 and a["op"] == RECORDER for a in acks)  # frame 0 lacks its source value
        outcome = recording.close(timeout_s=10)
        ack_sub.undeclare()
        ring.close()
    finally:
        for session in (publisher, launcher, hub):
            session.close()
    assert outcome["lost"] == {keys.data("source", "value"): 1}
    assert recording_outcome(tmp_path / "run.mcap")["lost"] == outcome["lost"]
    assert describe_loss(outcome) == "lost 1 payloads (source/value 1)"
    written = Counter(m.topic for m in read_log(tmp_path / "run.mcap"))
    assert written[keys.data("source", "value")] == 1 and written[keys.data("sink", "total")] == 2


def test_a_graph_whose_log_lacks_messages_exits_non_zero_naming_them(tmp_path, hub_endpoint):
    """A sink that returns no output for its declared port: its frames are closed without it once
    every sink acked, so the graph finishes, but the launcher says what the log lacks."""
    graph_file = toy_graph(tmp_path, hub_endpoint, frames=4)
    graph = yaml.safe_load(graph_file.read_text())
    for op in graph["operators"]:
        if op["id"] == "sink":
            op["params"]["silent"] = True
    graph_file.write_text(yaml.safe_dump(graph, sort_keys=False))
    log = tmp_path / "run.mcap"
    result = subprocess.run(
        [*UMAD, "launch", str(graph_file), "--record", str(log)],
        capture_output=True,
        text=True,
        timeout=180,
        env=umad_env(),
        cwd=REPO,
    )
    assert result.returncode == EXIT_INCOMPLETE, result.stdout[-3000:] + result.stderr[-3000:]
    assert "is incomplete: frames lacking: sink/total 8" in result.stderr  # 2 runs of 4 frames
    assert recording_outcome(log)["lacking"] == {"umad/toy/sink/total": 8}


def test_a_second_ctrl_c_kills_at_once(tmp_path, hub_endpoint):
    """An operator busy in a 60 s frame ignores the first SIGINT's SIGTERM for longer than the
    launcher waits; a second Ctrl-C does not wait at all."""
    graph = toy_graph(tmp_path, hub_endpoint, frames=50, delay=60.0)
    proc = subprocess.Popen(
        [*UMAD, "launch", str(graph), "--record", str(tmp_path / "run.mcap")],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=umad_env(),
        cwd=REPO,
    )
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if "ready" in line and "double" in line:
            break
    time.sleep(2.0)  # the first frames are in `double`'s 60 s sleep
    proc.send_signal(signal.SIGINT)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    second = time.monotonic()
    proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert time.monotonic() - second < 2.0
    assert sum(1 for _ in read_log(tmp_path / "run.mcap")) >= 0  # closed and readable
    left = subprocess.run(["pgrep", "-f", "--", f"--graph {graph}"], capture_output=True, text=True).stdout
    assert left.strip() == ""
