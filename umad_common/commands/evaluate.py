"""`umad eval`: the whole UMAD evaluation in one command. Its steps:

0. checks: every input (data, models and their records, graph, --out, the hub's port) before anything
   starts or is written; a wrong one is one line and exit code 2;
1. data: `--data DIR` (drives with anomaly labels: AnoVox folders, ROS 2 bags or Foxglove MCAPs with a
   labels topic; its `anomalous/` part if it has one), or the built-in synthetic benchmark, generated
   into OUT/benchmark with a seed the shipped models never saw;
2. the graph (default graph.yaml: world model, all five differences, fusion, ground-truth and
   unsupervised segmenters, refiners, MNAD, accumulator; SAM too with --sam-checkpoint) runs with
   the chosen models, recorded to OUT/run.mcap;
3. the sweep computes the paper's ablation table from that one log and writes the report to OUT.

`--protocol paper` scores every 10th frame and writes the table in the paper's layout; `quick`
(the default) scores every 2nd frame and writes one line per configuration.

example: umad eval --out umad-eval   (the built-in benchmark and the shipped models; its time on 2
cores: docs/benchmarks.md); umad eval --data DIR --out OUT [--topics camera=/a,labels=/b] for your own drives
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import yaml

from umad_common import ASSETS, SAM_ENV_SCRIPT
from umad_common.commands.checks import (
    InputError,
    checked_graph,
    evaluation_drives,
    existing_file,
    free_hub_port,
    lidar_notice,
    model_file,
    print_notice,
    writable_output,
)
from umad_common.commands.common import DEFAULT_GRAPH, add_frames_argument, add_out_argument, add_topics_argument

log = logging.getLogger("umad.eval")

BENCHMARK_SEED = 1  # the shipped models were trained on seed 0's normal drives
PROTOCOLS = {  # name -> (every k-th frame scored, report table layout)
    "quick": (2, "long"),
    "paper": (10, "paper"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = __doc__  # the steps it runs
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        help="drives to evaluate, with anomaly labels (default: generate the built-in benchmark)",
    )
    add_topics_argument(parser)
    parser.add_argument(
        "--allow-truncated", action="store_true", help="read a recording cut off by a crash up to the damage"
    )
    parser.add_argument(
        "--graph", type=Path, default=DEFAULT_GRAPH, help="graph file (default: the built-in graph.yaml)"
    )
    add_out_argument(parser, help="report folder (default: ./umad-eval)", required=False, default=Path("umad-eval"))
    parser.add_argument(
        "--world-model", type=Path, default=ASSETS / "world_model.safetensors", help="world model weights"
    )
    parser.add_argument(
        "--features", type=Path, default=ASSETS / "feature_net.safetensors", help="perceptual feature net weights"
    )
    parser.add_argument(
        "--vgg-weights",
        type=Path,
        default=None,
        help="torchvision VGG16 state dict: ImageNet perceptual distance instead of the feature net",
    )
    parser.add_argument("--mnad", type=Path, default=ASSETS / "mnad.safetensors", help="MNAD baseline weights")
    parser.add_argument(
        "--protocol",
        choices=sorted(PROTOCOLS),
        default="quick",
        help="quick: every 2nd frame, one table line per configuration (default); "
        "paper: every 10th frame, the paper's table layout",
    )
    parser.add_argument(
        "--every",
        type=int,
        default=None,
        help="score every k-th frame of each scenario (default: the protocol's); the world model still sees "
        "every frame",
    )
    parser.add_argument(
        "--scenarios",
        type=int,
        default=12,
        help="built-in benchmark: anomalous scenarios to generate (3 per anomaly category)",
    )
    add_frames_argument(parser, 100, help="built-in benchmark: frames per scenario")
    parser.add_argument(
        "--sam-checkpoint", type=Path, default=None, help="segment-anything checkpoint: adds the SAM mask rows"
    )
    parser.add_argument("--sam-model", default="vit_b", choices=["vit_b", "vit_l", "vit_h"])
    parser.add_argument(
        "--sam-python",
        default=".venv-sam/bin/python",
        help=f"interpreter of the environment with segment-anything (built by `bash {SAM_ENV_SCRIPT} .venv-sam`)",
    )
    parser.add_argument("--hub", default=None, help="hub endpoint (default: the graph's)")
    parser.add_argument(
        "--allow-incomplete",
        action="store_true",
        help="report even if the recorded run lost messages (refused otherwise); the protocol line says what "
        "each channel lacks",
    )
    parser.add_argument(
        "--set", action="append", default=[], metavar="OP.PARAM=VALUE", help="any other parameter override"
    )


def check_inputs(args: argparse.Namespace) -> Path | None:
    """Everything `umad eval` was given, checked before anything starts or is written (`args.every`
    already the protocol's when not given). Returns the folder it scores: `--data`'s drives, or None
    for the built-in benchmark, generated later."""
    if args.every < 1:
        raise InputError.of(f"--every {args.every}", "is below 1", "k >= 1: every k-th frame scored")
    for value, flag in ((args.scenarios, "--scenarios"), (args.frames, "--frames")):
        if value < 1:
            raise InputError.of(f"{flag} {value}", "is below 1", "at least 1")
    writable_output(args.out, "--out")
    model_file(args.world_model, "--world-model", "world model")
    if args.vgg_weights:
        existing_file(args.vgg_weights, "--vgg-weights", "a torchvision VGG16 state dict")
    else:
        model_file(args.features, "--features", "perceptual feature net")
    model_file(args.mnad, "--mnad", "MNAD baseline")
    if args.sam_checkpoint:
        existing_file(args.sam_checkpoint, "--sam-checkpoint", "a segment-anything checkpoint")
        existing_file(
            Path(args.sam_python),
            "--sam-python",
            f"the python of the SAM environment (build it with `bash {SAM_ENV_SCRIPT} .venv-sam`)",
        )
    source, scenarios = (
        evaluation_drives(args.data, "--data", args.topics, args.allow_truncated) if args.data else (None, [])
    )
    graph = checked_graph(args.graph, local=True)
    free_hub_port(args.hub or graph.spec.hub, "--hub" if args.hub else f"{args.graph}: hub")
    if source is None:  # the benchmark's folder does not exist yet: the graph without its data
        checked_graph(args.out / "graph.yaml", args.set, local=True, data=_eval_graph(args, args.out / "benchmark"))
        return None
    run_graph = checked_graph(
        args.out / "graph.yaml", args.set, local=True, runs=True, data=_eval_graph(args, source.resolve())
    )
    print_notice(lidar_notice(run_graph, scenarios, "--data"))
    return source.resolve()


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    args.every, layout = every_and_layout(args.protocol, args.every)
    source = check_inputs(args)

    from umad_common.dataflow.api.exit_codes import EXIT_INCOMPLETE, EXIT_STOPPED
    from umad_common.dataflow.launch.launcher import Launcher
    from umad_common.datasets.formats import anomalous_root
    from umad_common.viz.headline import SCORES, percent, weakest_drive_text
    from umad_common.viz.report import write_report
    from umad_replay.sweep import sweep_log

    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    phases: dict[str, float] = {}  # phase -> wall seconds, printed with the total
    if source is None:
        with timed(phases, "generation"):
            data = _builtin_benchmark(out / "benchmark", args.scenarios, args.frames)
        source = anomalous_root(data)
    graph_file = out / "graph.yaml"
    graph_file.write_text(yaml.safe_dump(_eval_graph(args, source), sort_keys=False))
    graph = checked_graph(str(graph_file), args.set, local=True, runs=True)
    record = out / "run.mcap"
    print(f"evaluating {source} -> {out}", flush=True)
    with timed(phases, "graph"):
        code = Launcher(graph, graph_file, sets=args.set, record=record, hub=args.hub).run()
    if code == EXIT_INCOMPLETE and not args.allow_incomplete:
        print(
            f"the recorded run {record} lacks messages (see above): no table from it; rerun, or pass "
            "--allow-incomplete and run `umad sweep --allow-incomplete` on it",
            file=sys.stderr,
        )
        return code
    if code == EXIT_STOPPED:
        print(f"stopped; the log so far is {record}", file=sys.stderr)
        return code
    if code not in (0, EXIT_INCOMPLETE):
        print(f"the graph failed (exit {code}); the log so far is {record}", file=sys.stderr)
        return code
    result = sweep_log(record, allow_incomplete=args.allow_incomplete, workers=os.cpu_count() or 1)
    phases["sweep"] = result.seconds
    with timed(phases, "report"):
        index = write_report(result, out, record, layout=layout)
    print(f"\n{(out / 'table.md').read_text()}")
    shipped = result_headline(out).get("shipped")
    if shipped:
        figures = ", ".join(f"{key} {percent(shipped[key])}" for key, _ in SCORES)
        print(
            f"shipped configuration ({shipped['masks']}, {shipped['weights_label']}): {figures}; weakest drive "
            f"{weakest_drive_text(shipped)}"
        )
    took = ", ".join(f"{phase} {seconds:.0f} s" for phase, seconds in phases.items())
    print(
        f"UMAD evaluation done in {time.perf_counter() - started:.0f} s ({took}); "
        f"report: {index} (and {out / 'index.html'})"
    )
    return 0


def result_headline(out: Path) -> dict:
    """The headline of the report just written in `out` (its results.json)."""
    import json

    return json.loads((out / "results.json").read_text())["headline"]


@contextmanager
def timed(phases: dict[str, float], phase: str) -> Iterator[None]:
    """Record the wall seconds of the block as `phases[phase]`."""
    start = time.perf_counter()
    try:
        yield
    finally:
        phases[phase] = time.perf_counter() - start


def every_and_layout(protocol: str, every: int | None) -> tuple[int, str]:
    """The frames scored (every k-th) and the report's table layout of a protocol; `every` overrides k."""
    protocol_every, layout = PROTOCOLS[protocol]
    return (protocol_every if every is None else every), layout


def _builtin_benchmark(folder: Path, scenarios: int, frames: int) -> Path:
    """Generate (once) the evaluation scenarios of the built-in world."""
    from tqdm import tqdm

    from umad_common.datasets.synthetic.generator import generate_benchmark

    marker = folder / f".complete-{scenarios}x{frames}-seed{BENCHMARK_SEED}"
    if marker.is_file():
        return folder
    if folder.exists():
        import shutil

        shutil.rmtree(folder)
    with tqdm(total=scenarios * frames, desc="generating benchmark", unit="frame") as bar:
        generate_benchmark(
            folder, 0, scenarios, frames, BENCHMARK_SEED, (384, 256), on_frame=bar.update, workers=os.cpu_count() or 1
        )
    marker.touch()
    return folder


def _eval_graph(args: argparse.Namespace, source: Path) -> dict:
    """The graph file with this evaluation's data, models and optional SAM branch filled in."""
    from umad_common.dataflow.api.graph import graph_base_dir

    graph_path = args.graph.resolve()
    data = yaml.safe_load(graph_path.read_text())
    data["base_dir"] = str(graph_base_dir(graph_path, data.get("base_dir")))
    by_kind: dict[str, list[dict]] = {}
    for op in data["operators"]:
        by_kind.setdefault(op.get("kind", ""), []).append(op)
    for op in by_kind.get("replayer", []):
        op.setdefault("params", {}).update({"source": str(source), "every": 1, "score_every": args.every})
        if args.data:
            op["params"].update({"topics": args.topics, "allow_truncated": args.allow_truncated})
    for op in by_kind.get("world_model", []):
        op.setdefault("params", {})["model"] = str(args.world_model.resolve())
    for op in by_kind.get("difference", []):
        params = op.setdefault("params", {})
        if params.get("metric") == "perceptual":
            params["features"] = str(args.features.resolve())
            if args.vgg_weights:
                params["vgg_weights"] = str(args.vgg_weights.resolve())
    for op in by_kind.get("mnad", []):
        op.setdefault("params", {})["weights"] = str(args.mnad.resolve())
    for op in by_kind.get("accumulator", []):
        op.setdefault("params", {})["out"] = str((args.out / "live_metrics.json").resolve())
    if args.sam_checkpoint:
        frame_src = next(op["inputs"]["frame"] for op in by_kind.get("segmenter", []))
        fused_src = next(op["inputs"]["fused"] for op in by_kind.get("mask_refiner", []))
        sam_python = Path(args.sam_python)
        data["operators"] += [
            {
                "id": "segment_sam",
                "kind": "segmenter",
                "python": str(sam_python.resolve()),
                "inputs": {"frame": frame_src},
                "params": {
                    "method": "sam",
                    "options": {"checkpoint": str(args.sam_checkpoint.resolve()), "model": args.sam_model},
                },
            },
            {
                "id": "refine_sam",
                "kind": "mask_refiner",
                "inputs": {"fused": fused_src, "masks": "segment_sam/masks"},
                "params": {"mode": "mean"},
            },
        ]
    return data
