"""`umad train world-model DATA --out MODEL`: train the world model on the normal drives of DATA.

Reads DATA/normal when it exists (a generated benchmark), else every drive under DATA (AnoVox folders,
ROS 2 bags, Foxglove MCAPs; `--topics` picks a recording's topics); never reads labels. Writes MODEL.safetensors, MODEL.json (the full model and training configs, the
command that trained it, held-out drives, loss history) and the resumable checkpoint
MODEL.train.pt (not needed to use the model). `--config MODEL.json` trains with the configs of a
saved model: `umad train world-model DATA --out NEW --config umad_common/assets/world_model.json`
rebuilds the shipped one.

`--nproc N` trains in N processes on this machine with torch.distributed (DDP: gloo on the CPU, NCCL
on GPUs, one per process), `--threads` split among them; every step trains the same `--batch-size`
windows, split over the processes. Across machines, start it with torchrun, which sets the ranks
(RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT) and replaces --nproc:
`torchrun --nnodes 2 --node-rank R --nproc-per-node 2 --master-addr HOST --master-port 29500
-m umad_common.cli train world-model DATA --out MODEL` on each machine (DATA at the same path on
every machine; the files are written by rank 0 on its machine).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
from dataclasses import asdict
from pathlib import Path

from umad_common.commands.checks import existing_file, training_inputs
from umad_common.commands.common import (
    add_data_argument,
    add_device_argument,
    add_epochs_argument,
    add_out_argument,
    add_seed_argument,
    add_topics_argument,
    resolve_device_or_exit,
)

DEFAULT_EPOCHS = 35


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_data_argument(parser)
    add_topics_argument(parser)
    add_out_argument(parser, help="output path without suffix, e.g. umad_common/assets/world_model")
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="a saved MODEL.json (or any JSON with 'config' and 'train_config'): train with its configs; "
        "flags given here override them",
    )
    add_epochs_argument(parser, None, help=f"total epochs (default {DEFAULT_EPOCHS}, or the --config's)")
    add_seed_argument(parser, None, help="seed of initialisation, window order and latent noise")
    parser.add_argument(
        "--resume", action="store_true", help="continue from MODEL.train.pt with the configs stored in it"
    )
    parser.add_argument(
        "--threads", type=int, default=2, help="torch CPU threads, split among --nproc processes (results depend on it)"
    )
    parser.add_argument(
        "--nproc",
        type=int,
        default=None,
        help="train in N processes on this machine (torch.distributed DDP; default 1; under torchrun its own count)",
    )
    parser.add_argument("--batch-size", type=int, default=None, help="windows per step (default from TrainConfig)")
    parser.add_argument("--sequence-length", type=int, default=None, help="model steps per window (default 8)")
    parser.add_argument(
        "--holdout", type=int, default=None, help="last N normal drives kept out for evaluation (default 1)"
    )
    parser.add_argument("--frame-step", type=int, default=None, help="dataset frames per model step (default 1)")
    parser.add_argument(
        "--relight",
        type=float,
        default=None,
        help="share of training windows re-lit with a random gamma, brightness and colour cast (default 0)",
    )
    parser.add_argument(
        "--lidar-head",
        action="store_true",
        help="train a lidar head with the model: it decodes the lidar view the `lidar` difference compares "
        "(`umad train lidar-head` adds one to a model trained without, leaving its camera weights as they are; "
        "trained together, the head cost the camera rows AP on the stress set: docs/experiments.md)",
    )
    add_device_argument(parser)


def configs_of(args: argparse.Namespace):
    """(model config, train config, epochs, seed) the command trains with: the code's defaults, or the
    `--config` file's, with the flags given on the command line on top."""
    from umad_common.models.world_model import WorldModelConfig
    from umad_common.training.world_model_step import TrainConfig

    model_config, train, epochs, seed = WorldModelConfig(), TrainConfig(), DEFAULT_EPOCHS, 0
    if args.config is not None:
        try:
            saved = json.loads(args.config.read_text())
            model_config = WorldModelConfig.from_dict(saved["config"])
            train = TrainConfig(**saved["train_config"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SystemExit(
                f"{args.config}: not a world model config ({exc}); expected JSON with 'config' and 'train_config' "
                "objects, as MODEL.json"
            ) from None
        epochs, seed = int(saved.get("epochs", epochs)), int(saved.get("seed", seed))
    overrides = {name: getattr(args, name) for name in ("batch_size", "sequence_length", "holdout", "relight")}
    try:
        train = TrainConfig(**{**asdict(train), **{k: v for k, v in overrides.items() if v is not None}})
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    if args.frame_step is not None:
        model_config.frame_step = args.frame_step
    if args.lidar_head:
        model_config.lidar_head = True
    epochs = epochs if args.epochs is None else args.epochs
    seed = seed if args.seed is None else args.seed
    if epochs < 1:
        raise SystemExit(f"--epochs is {epochs}; expected at least 1")
    return model_config, train, epochs, seed


def processes_of(args: argparse.Namespace, batch_size: int) -> int:
    """How many training processes share this machine: --nproc, or torchrun's per-machine count
    (then --nproc must be left out); each step's `batch_size` windows must split over all of them."""
    from umad_common.training import distributed

    if distributed.started_by_torchrun():
        if args.nproc is not None:
            raise SystemExit(
                f"--nproc {args.nproc}: under torchrun the processes are torchrun's (--nproc-per-node); leave --nproc out"
            )
        processes, world = distributed.processes_on_this_machine(), int(os.environ["WORLD_SIZE"])
    else:
        processes = world = 1 if args.nproc is None else args.nproc
        if processes < 1:
            raise SystemExit(f"--nproc {processes}: expected at least 1 process")
    if batch_size % world:
        raise SystemExit(
            f"--batch-size {batch_size} does not split over {world} processes; expected a multiple of {world}"
        )
    return processes


def command_line(args: argparse.Namespace) -> str:
    """The command as it was given (flags left at their defaults omitted), for the model's record."""
    words = ["umad", "train", "world-model", str(args.data), "--out", str(args.out)]
    words += ["--topics", args.topics] if args.topics else []
    for flag in ("config", "epochs", "seed", "batch_size", "sequence_length", "holdout", "frame_step"):
        if getattr(args, flag) is not None:
            words += ["--" + flag.replace("_", "-"), str(getattr(args, flag))]
    words += ["--threads", str(args.threads)] + (["--device", args.device] if args.device != "auto" else [])
    words += ["--nproc", str(args.nproc)] if args.nproc is not None else []
    words += ["--lidar-head"] if args.lidar_head else []
    words += ["--resume"] if args.resume else []
    return shlex.join(words)


def run(args: argparse.Namespace) -> int:
    training_inputs(args.data, args.out, "", args.topics)
    if args.config:
        existing_file(args.config, "--config", "a saved MODEL.json (or any JSON with 'config' and 'train_config')")
    # On a shared machine, OpenMP threads that spin while waiting make 2 threads slower than 1;
    # passive waiting must be chosen before torch loads its OpenMP runtime.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from umad_common.models.weights import weight_paths
    from umad_common.training import distributed
    from umad_common.training.train_world_model import train_world_model

    model_config, train, epochs, seed = configs_of(args)
    processes = processes_of(args, train.batch_size)
    device = resolve_device_or_exit(args.device)
    training = dict(
        data=args.data,
        out=args.out,
        epochs=epochs,
        seed=seed,
        resume=args.resume,
        threads=max(1, args.threads // processes),
        model_config=model_config,
        train_config=train,
        command=command_line(args),
        device=str(device),
        topics=args.topics,
    )
    if distributed.started_by_torchrun():
        distributed.run_rank(train_world_model, training)
        if int(os.environ["RANK"]) != 0:
            return 0
    elif processes > 1:
        distributed.run_processes(processes, train_world_model, training)
    else:
        train_world_model(**training)
    record = json.loads(weight_paths(args.out)[1].read_text())
    last = record["history"][-1]
    summary = {k: round(v, 5) if isinstance(v, float) else v for k, v in last.items()}
    print(json.dumps({"out": str(args.out), "train_seconds": record["train_seconds"], **summary}))
    return 0
