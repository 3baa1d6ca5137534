"""`umad train segmenter DATA --out FILE`: train the label-free segment net on normal drives.

Reads DATA/normal when it exists (a generated benchmark), else every Scenario_* under DATA; never
reads labels. Writes FILE (safetensors) and its .json beside it: the net's config, the training
config, the command, the loss and seconds per epoch and the machine's load while it trained. The
`learned` segmenter method (and `geometry_learned`) reads it.
"""

from __future__ import annotations

import argparse
import logging
import os
import shlex

from umad_common.commands.checks import training_inputs
from umad_common.commands.common import (
    add_data_argument,
    add_device_argument,
    add_epochs_argument,
    add_frames_argument,
    add_out_argument,
    add_seed_argument,
    add_topics_argument,
    resolve_device_or_exit,
)

log = logging.getLogger("umad.train.segmenter")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_data_argument(parser)
    add_topics_argument(parser)
    add_out_argument(parser)
    # left None: SegmenterTrainingConfig's defaults apply, and `command_line` records only the flags given
    add_epochs_argument(parser, None, help="passes over the loaded frames (default 4)")
    add_seed_argument(parser, None, help="random seed (default 0)")
    add_frames_argument(parser, None, help="at most this many frames, spread over all scenarios (default 1200)")
    parser.add_argument("--batch-size", type=int, default=None, help="frames per step (default 8)")
    parser.add_argument("--clusters", type=int, default=None, help="prototypes, i.e. segment classes (default 24)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (results depend on it)")
    add_device_argument(parser)


FLAGS = {"epochs": "epochs", "seed": "seed", "frames": "max_frames", "batch_size": "batch_size"}  # flag -> field


def configs_of(args: argparse.Namespace):
    """(net config, training config) the command trains with: the defaults with the given flags on top."""
    from umad_common.models.segment_net import SegmentNetConfig
    from umad_common.training.train_segmenter import SegmenterTrainingConfig

    overrides = {field: getattr(args, flag) for flag, field in FLAGS.items() if getattr(args, flag) is not None}
    try:
        train = SegmenterTrainingConfig(**overrides)
    except ValueError as exc:
        raise SystemExit(f"umad train segmenter: {exc}") from None
    net = SegmentNetConfig() if args.clusters is None else SegmentNetConfig(clusters=args.clusters)
    if net.clusters < 2:
        raise SystemExit(f"--clusters {net.clusters}: expected at least 2")
    return net, train


def command_line(args: argparse.Namespace) -> str:
    """The command as it was given (flags left at their defaults omitted), for the model's record."""
    words = ["umad", "train", "segmenter", str(args.data), "--out", str(args.out)]
    words += ["--topics", args.topics] if args.topics else []
    for flag in (*FLAGS, "clusters"):
        if getattr(args, flag) is not None:
            words += ["--" + flag.replace("_", "-"), str(getattr(args, flag))]
    words += ["--threads", str(args.threads)] + (["--device", args.device] if args.device != "auto" else [])
    return shlex.join(words)


def run(args: argparse.Namespace) -> int:
    training_inputs(args.data, args.out, ".safetensors", args.topics)
    # passive OpenMP waiting (see train_world_model): must be set before torch loads
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch

    from umad_common.models.segment_net import save_segment_net
    from umad_common.training.train_features import load_normal_rgb
    from umad_common.training.train_segmenter import train_segment_net

    net_cfg, train_cfg = configs_of(args)
    torch.set_num_threads(args.threads)
    device = resolve_device_or_exit(args.device)
    frames, heldout = load_normal_rgb(args.data, train_cfg, args.topics)
    model, record = train_segment_net(frames, train_cfg, net_cfg, device)
    record = {"command": command_line(args), "data": str(args.data), "heldout_drives": heldout} | record
    save_segment_net(model, args.out, {"training": record})
    log.info("wrote %s (+ %s) after %s s", args.out, args.out.with_suffix(".json").name, record["seconds"])
    return 0
