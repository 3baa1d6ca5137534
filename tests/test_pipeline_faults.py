"""The real UMAD graph under faults: SIGKILL of a difference worker and of the world model mid-stream
ends with final metrics identical to a fault-free run (nothing lost, nothing counted twice, the
world model's state rebuilt by re-observing its run)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import REPO, DrainedUmad, free_port
from umad_common.dataflow.transport.bus import open_client

pytestmark = pytest.mark.slow
FRAMES = 16


def pipeline_graph(
    tmp_path: Path, data: Path, name: str, score_every: int = 1, world_models: int = 1, runs_in_flight: int = 1
) -> Path:
    graph = yaml.safe_load((REPO / "graph.yaml").read_text())
    graph.update(hub=f"tcp/127.0.0.1:{free_port()}", base_dir=str(REPO))
    for op in graph["operators"]:
        if op["kind"] == "replayer":
            op["params"].update(
                source=str(data / "anomalous"),
                window=4,
                ack_timeout_s=3.0,
                score_every=score_every,
                runs_in_flight=runs_in_flight,
            )
        if op["kind"] == "world_model":
            op["replicas"] = world_models
        if op["kind"] == "accumulator":
            op["params"]["out"] = str(tmp_path / f"{name}.json")
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(graph, sort_keys=False))
    return path


def run_graph(graph: Path, kill_after: dict[str, int], replica: int = 0) -> tuple[str, set[str]]:
    """Launch; SIGKILL replica `replica` of operator OP once its stats report `kill_after[OP]`
    frames in. Returns the output and the operators killed."""
    hub = yaml.safe_load(graph.read_text())["hub"]
    launch = DrainedUmad("launch", str(graph))
    killed: set[str] = set()
    session = open_client(hub)
    try:
        frames_in: dict[str, int] = {}
        sub = session.declare_subscriber(
            f"umad/umad/_stats/*/r{replica}",
            lambda s: frames_in.update({str(s.key_expr).split("/")[-2]: json.loads(s.payload.to_bytes())["frames_in"]}),
        )
        deadline = time.monotonic() + 300
        while launch.proc.poll() is None and killed != set(kill_after) and time.monotonic() < deadline:
            for op, after in kill_after.items():
                if op not in killed and frames_in.get(op, 0) >= after:
                    pid = subprocess.run(
                        ["pgrep", "-f", "--", f"--graph {graph} --op {op} --replica {replica}"],
                        capture_output=True,
                        text=True,
                    ).stdout.split()
                    if pid:
                        os.kill(int(pid[0]), signal.SIGKILL)
                        killed.add(op)
            time.sleep(0.05)
        sub.undeclare()
    finally:
        session.close()
    out = launch.wait(timeout=400)
    assert launch.proc.returncode == 0, out[-5000:]
    return out, killed


def test_killed_worker_and_world_model_leave_the_metrics_exactly_as_without_faults(tmp_path):
    from umad_common.datasets.synthetic.generator import generate_benchmark

    generate_benchmark(tmp_path / "data", 0, 1, FRAMES, 7, (192, 128))
    clean_out, _ = run_graph(pipeline_graph(tmp_path, tmp_path / "data", "clean"), {})
    assert "did not stop after SIGTERM" not in clean_out  # every operator stopped within its grace period
    out, killed = run_graph(pipeline_graph(tmp_path, tmp_path / "data", "faulty"), {"diff_ssim": 4, "world_model": 8})

    assert killed == {"diff_ssim", "world_model"}
    assert "[diff_ssim.0] exited with -9; restart 1/3" in out and "[world_model.0] exited with -9; restart 1/3" in out
    assert "asking the sources to resend them" in out  # the world model re-observed its run
    clean = json.loads((tmp_path / "clean.json").read_text())
    faulty = json.loads((tmp_path / "faulty.json").read_text())
    assert set(clean["overall"]) >= {"fusion", "refine_gt", "refine_unsup", "mnad"}
    assert faulty == clean  # every AP / FPR95 / AUROC and pixel count, to the last bit
    assert all(m["n_anomaly"] > 0 for m in clean["overall"].values())


def test_a_killed_keyed_world_model_replica_leaves_the_metrics_of_one_replica(tmp_path):
    """Two drives side by side on two keyed world model replicas; the replica that owns the first
    drive is killed mid-drive, a survivor takes the drive over from its first frame: the metrics
    are those of the default graph's one world model."""
    from umad_common.dataflow.delivery.ordered import rendezvous_score
    from umad_common.datasets.synthetic.generator import generate_benchmark

    generate_benchmark(tmp_path / "data", 0, 2, FRAMES, 7, (192, 128))
    first = sorted(p.name for p in (tmp_path / "data" / "anomalous").glob("Scenario_*"))[0]
    owner = max((0, 1), key=lambda r: rendezvous_score(first, f"r{r}"))
    run_graph(pipeline_graph(tmp_path, tmp_path / "data", "clean"), {})
    keyed = pipeline_graph(tmp_path, tmp_path / "data", "keyed", world_models=2, runs_in_flight=2)
    out, killed = run_graph(keyed, {"world_model": 6}, replica=owner)

    assert killed == {"world_model"}
    assert "its replica is gone; taking it over from its first frame" in out
    clean = json.loads((tmp_path / "clean.json").read_text())
    assert json.loads((tmp_path / "keyed.json").read_text()) == clean  # to the last bit
    assert all(m["n_anomaly"] > 0 for m in clean["overall"].values())


def test_score_every_k_scores_every_kth_frame_while_the_world_model_sees_all(tmp_path):
    from umad_common.datasets.synthetic.generator import generate_benchmark
    from umad_common.models.world_model import load_world_model

    generate_benchmark(tmp_path / "data", 0, 1, FRAMES, 7, (192, 128))
    out, _ = run_graph(pipeline_graph(tmp_path, tmp_path / "data", "every2", score_every=2), {})
    config = load_world_model(REPO / "umad_common/assets/world_model")[0].config
    scored = json.loads((tmp_path / "every2.json").read_text())["overall"]
    for producer in ("fusion", "refine_gt", "refine_unsup"):
        pixels = sum(scored[producer][k] for k in ("n_anomaly", "n_normal", "n_ignored"))
        assert pixels == FRAMES // 2 * config.image_height * config.image_width, producer
    assert f"stopped after {FRAMES} frames" in out.split("[world_model.0]", 1)[1]
