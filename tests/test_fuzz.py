"""Fuzz: >= 10,000 malformed messages at every input of the real pipeline while it runs.

No operator may crash; every malformed payload is counted in the stats of every operator that
received it; the stream still finishes with every frame evaluated.
"""

from __future__ import annotations

import json
import re
import time

import msgpack
import numpy as np
import pytest
import yaml
import zenoh

from tests.conftest import REPO, DrainedUmad
from umad_common.dataflow.api.graph import load_graph
from umad_common.dataflow.api.messages import Message, encode
from umad_common.dataflow.transport.bus import Keys, open_client

pytestmark = pytest.mark.slow
N_PAYLOADS = 10_000


def malformed_payloads(n: int, seed: int = 0) -> list[bytes]:
    """Random bytes, non-map msgpack, wrong versions, lying shapes, huge declared sizes, bad dtypes."""
    rng = np.random.default_rng(seed)
    good = encode(Message("fuzz", 0, arrays={"rgb": np.zeros((4, 4, 3), np.uint8)}))

    def header(**kw):
        obj = {
            "v": 1,
            "run": "fuzz",
            "seq": int(rng.integers(0, 1000)),
            "stamp_ns": 0,
            "producer": "fuzz",
            "meta": {},
            "arrays": {"rgb": {"dtype": "|u1", "shape": [4, 4, 3], "data": b"\0" * 48}},
        }
        obj.update(kw)
        return msgpack.packb(obj, use_bin_type=True)

    makers = [
        lambda: rng.bytes(int(rng.integers(0, 300))),
        lambda: msgpack.packb([1, 2, 3]),
        lambda: header(v=int(rng.integers(2, 100))),
        lambda: header(arrays={"rgb": {"dtype": "|u1", "shape": [512, 768, 3], "data": b"\0" * 48}}),
        lambda: header(arrays={"rgb": {"dtype": "<f4", "shape": [2**31 - 1, 2**31 - 1], "data": b""}}),
        lambda: header(arrays={"rgb": {"dtype": "|O", "shape": [1], "data": b"\0" * 8}}),
        lambda: header(seq=-5),
        lambda: header(meta="not a map"),
        lambda: good[: int(rng.integers(1, len(good)))],
    ]
    return [makers[i % len(makers)]() for i in range(n)]


def test_ten_thousand_malformed_messages_crash_nothing_and_are_all_counted(tmp_path):
    from umad_common.datasets.synthetic.generator import generate_benchmark

    generate_benchmark(tmp_path / "data", 0, 1, 12, 3, (192, 128))
    port = 7600 + int(time.time()) % 300
    hub = f"tcp/127.0.0.1:{port}"
    data = yaml.safe_load((REPO / "graph.yaml").read_text())
    data.update(hub=hub, base_dir=str(REPO))
    for op in data["operators"]:
        if op["kind"] == "replayer":
            # Realtime pacing at 0.3 Hz keeps the 12-frame stream going for 40 s whatever the
            # machine's speed, so every operator is still up while the garbage arrives.
            op["params"].update(source=str(tmp_path / "data" / "anomalous"), pacing="realtime", rate_hz=0.3)
    graph_file = tmp_path / "graph.yaml"
    graph_file.write_text(yaml.safe_dump(data, sort_keys=False))
    graph = load_graph(graph_file)
    keys = Keys(graph.name)
    targets = sorted(
        {
            f"{op}/{out}"
            for spec in graph.spec.operators
            for port in spec.inputs
            for src in spec.sources_of(port)
            for op, out in graph.producers(src)
        }
    )

    stats: dict[str, dict] = {}
    launch = DrainedUmad("launch", str(graph_file))
    session = open_client(hub)
    try:
        sub = session.declare_subscriber(
            f"{keys.root}/_stats/**",
            lambda s: stats.update({str(s.key_expr).split("/_stats/")[1]: json.loads(s.payload.to_bytes())}),
        )
        deadline = time.monotonic() + 240
        consumers = [s.id for s in graph.spec.operators if s.inputs]
        while time.monotonic() < deadline and not all(f"{op}/r0" in stats for op in consumers):
            time.sleep(0.2)
        assert all(f"{op}/r0" in stats for op in consumers), sorted(stats)
        payloads = malformed_payloads(N_PAYLOADS)
        sent: dict[str, int] = {}
        pubs = {
            t: session.declare_publisher(keys.data(*t.split("/")), congestion_control=zenoh.CongestionControl.BLOCK)
            for t in targets
        }
        for i, payload in enumerate(payloads):
            target = targets[i % len(targets)]
            pubs[target].put(payload)
            sent[target] = sent.get(target, 0) + 1
        expected = {}
        for spec in graph.spec.operators:
            wired = {
                f"{op}/{out}"
                for port in spec.inputs
                for src in spec.sources_of(port)
                for op, out in graph.producers(src)
            }
            expected[spec.id] = sum(n for t, n in sent.items() if t in wired)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and any(
            stats[f"{op}/r0"]["bad_messages"] < n for op, n in expected.items() if n
        ):
            time.sleep(0.5)
        counted = {op: stats[f"{op}/r0"]["bad_messages"] for op, n in expected.items() if n}
        sub.undeclare()
    finally:
        session.close()
    out = launch.wait(timeout=600)
    assert launch.proc.returncode == 0, out[-5000:]
    assert sum(sent.values()) == N_PAYLOADS
    assert counted == {op: n for op, n in expected.items() if n}
    assert "restart" not in out  # no operator crashed
    assert re.search(r"\[accumulator\.0\].*stopped after 12 frames", out), out[-3000:]  # every frame evaluated
