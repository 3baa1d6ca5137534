"""`umad bench [bus|metrics|differences|predictors|scaling|segmenters|pipeline|record|control|live|train|data|all] [--out FILE.json]`;
`umad bench scaling --op world_model` replicates the world model instead of the perceptual difference.

Each bench measures both sides of its ratio in the same run on the same machine, so the ratio is
meaningful where the absolute numbers are not. Results are printed as Markdown and, with --out,
written as JSON (and Markdown beside it).
"""

from __future__ import annotations

import json
from pathlib import Path

from umad_common.commands.checks import InputError, drives, free_hub_port, model_file, writable_output
from umad_common.commands.common import add_frames_argument, add_out_argument, add_seed_argument

BENCHES = (
    "bus",
    "metrics",
    "differences",
    "predictors",
    "scaling",
    "segmenters",
    "pipeline",
    "record",
    "control",
    "live",
    "train",
    "data",
)
HUB_BENCHES = {"bus", "scaling", "record", "live", "control", "pipeline"}  # they start graphs on --hub


def add_arguments(parser):
    parser.add_argument("which", nargs="?", default="all", choices=[*BENCHES, "all"])
    add_out_argument(parser, help="write results as JSON (and .md beside it)", required=False)
    add_frames_argument(parser, None, help="frames per bench, commands for control (default: each bench's own)")
    parser.add_argument("--pixels", type=int, default=10**8, help="pixels for the metrics bench")
    parser.add_argument(
        "--op",
        choices=("perceptual", "world_model"),
        default="perceptual",
        help="scaling: the operator replicated, the perceptual difference (stateless: frames split by seq) or the "
        "world model (ordered: keyed replicas, each drive to one replica)",
    )
    parser.add_argument(
        "--drives", type=int, default=4, help="scaling --op world_model: generated drives, sent side by side"
    )
    parser.add_argument("--hub", default="tcp/127.0.0.1:7449", help="loopback endpoint the bench graphs use")
    parser.add_argument(
        "--shm-pool-mib", type=int, default=None, help="bus: the graph's `shm_pool_mib` (default: Zenoh's 16 MiB)"
    )
    parser.add_argument(
        "--against",
        choices=["dora"],
        default=None,
        help="bus: also run the relay as a dora-rs dataflow (the `dora` extra) and print the ratios",
    )
    parser.add_argument(
        "--security-only",
        action="store_true",
        help="bus: only its runs through the hub over plain TCP, mutual TLS, and mutual TLS with access control",
    )
    parser.add_argument(
        "--data", type=Path, default=None, help="segmenters, control, train: AnoVox drives (default: generated)"
    )
    parser.add_argument(
        "--nproc", type=int, default=2, help="train: training processes measured against one (default 2)"
    )
    parser.add_argument("--tune", action="store_true", help="segmenters: measure a parameter grid per method")
    parser.add_argument(
        "--methods", nargs="+", default=None, help="segmenters: these methods only (default: every registered one)"
    )
    parser.add_argument("--world-model", type=Path, default=None, help="segmenters: also measure refined pixel AP")
    add_seed_argument(parser, 2, help="segmenters: seed of the generated drives (2: validation; eval uses 1)")


def run(args) -> int:
    which = BENCHES if args.which == "all" else (args.which,)
    if args.out:
        writable_output(args.out, "--out", folder=False)
    if args.data:
        drives(args.data, "--data")
    if args.world_model:
        model_file(args.world_model, "--world-model", "world model")
    if set(which) & HUB_BENCHES:
        free_hub_port(args.hub, "--hub")
    if args.drives < 1:
        raise InputError.of("--drives", args.drives, "at least 1 drive")
    results = {}
    for name in which:
        print(f"running bench {name} ...", flush=True)
        results[name] = _run_one(name, args)
    md = to_markdown(results)
    print(md)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2))
        args.out.with_suffix(".md").write_text(md)
    return 0


def _run_one(name: str, args) -> dict:
    if name == "bus":
        from umad_common.benchmarks.bus import bench_bus

        return bench_bus(
            frames=args.frames or 2000,
            hub=args.hub,
            shm_pool_mib=args.shm_pool_mib,
            security_only=args.security_only,
            against=args.against,
        )
    if name == "metrics":
        from umad_common.benchmarks.metrics import bench_metrics

        return bench_metrics(args.pixels)
    if name == "differences":
        from umad_common.benchmarks.differences import bench_differences

        return bench_differences(frames=args.frames or 20)
    if name == "predictors":
        from umad_common.benchmarks.predictors import bench_predictors

        return bench_predictors(frames=args.frames or 40)
    if name == "scaling" and args.op == "world_model":
        from umad_common.benchmarks.scaling import bench_world_model_scaling

        return bench_world_model_scaling(drives=args.drives, frames=args.frames or 40, hub=args.hub)
    if name == "scaling":
        from umad_common.benchmarks.scaling import bench_scaling

        return bench_scaling(frames=args.frames or 400, hub=args.hub)
    if name == "segmenters":
        from umad_common.benchmarks.segmenters import bench_segmenters

        return bench_segmenters(
            args.data,
            methods=args.methods,
            tune=args.tune,
            world_model=args.world_model,
            max_frames=args.frames or 0,
            seed=args.seed,
        )
    if name == "record":
        from umad_common.benchmarks.record import bench_record

        return bench_record(frames=args.frames or 30, hub=args.hub)
    if name == "live":
        from umad_common.benchmarks.live import bench_live

        return bench_live(frames=args.frames or 600, hub=args.hub)
    if name == "control":
        from umad_common.benchmarks.control import bench_control

        return bench_control(rounds=args.frames or 20, hub=args.hub, data=args.data)
    if name == "train":
        from umad_common.benchmarks.train import bench_train

        return bench_train(processes=args.nproc, data=args.data)
    if name == "data":
        from umad_common.benchmarks.data import bench_data

        return bench_data(frames=args.frames or 100)
    from umad_common.benchmarks.pipeline import bench_pipeline

    return bench_pipeline(frames=args.frames or 30, hub=args.hub)


def to_markdown(results: dict) -> str:
    lines = ["| bench | measure | value |", "|---|---|---|"]
    for bench, res in results.items():
        for key, value in _flatten(res):
            lines.append(f"| {bench} | {key} | {_text(value)} |")
    return "\n".join(lines)


def _text(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return ", ".join(_text(v) for v in value)
    return str(value)


def _flatten(obj: dict, prefix: str = ""):
    for key, value in obj.items():
        if isinstance(value, dict):
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value
