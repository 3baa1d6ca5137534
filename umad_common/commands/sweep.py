"""`umad sweep LOG --out DIR`: the paper's ablation table and the report from a recorded log, no model run."""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

from umad_common.commands.checks import InputError, recorded_log, writable_output
from umad_common.commands.common import add_out_argument

log = logging.getLogger("umad.sweep")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", type=Path, help="MCAP log recorded by `umad eval` / the recorder")
    add_out_argument(parser, help="report folder (created): results.json, table.md/csv, PNGs, index.md/html")
    parser.add_argument("--every", type=int, default=1, help="evaluate frames with seq %% every == 0 (default 1: all)")
    parser.add_argument(
        "--lag", type=int, default=32, help="frames a run must move on before a frame counts as complete (default 32)"
    )
    parser.add_argument(
        "--no-components",
        action="store_true",
        help="skip the second read of the log (SegmentMeIfYouCan component metrics, per-scenario figures of the best rows)",
    )
    parser.add_argument(
        "--layout",
        choices=["long", "paper"],
        default="long",
        help="table.md: one line per configuration (long) or the paper's layout (a line per weight row)",
    )
    parser.add_argument(
        "--allow-incomplete",
        action="store_true",
        help="report on a log whose recorder lost messages (refused otherwise); the protocol line says what "
        "each channel lacks",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="processes sharing the weight rows, then the frames of the component pass (default: the machine's "
        "cores; the same result)",
    )
    parser.add_argument(
        "--overlays",
        type=int,
        default=6,
        help="overlay grids for this many frames with the largest anomalies (default 6)",
    )


def run(args: argparse.Namespace) -> int:
    recorded_log(args.log, "log")
    if args.workers is None:
        args.workers = os.cpu_count() or 1
    checked = (("--every", args.every, 1), ("--lag", args.lag, 0), ("--overlays", args.overlays, 0))
    for flag, value, least in (*checked, ("--workers", args.workers, 1)):
        if value < least:
            raise InputError.of(f"{flag} {value}", f"is below {least}", f"at least {least}")
    writable_output(args.out, "--out")

    from umad_common.viz.report import write_report
    from umad_replay.sweep import sweep_log

    result = sweep_log(
        args.log,
        lag=args.lag,
        every=args.every,
        overlay_frames=args.overlays,
        components=not args.no_components,
        allow_incomplete=args.allow_incomplete,
        workers=args.workers,
    )
    if result.stats.truncated:
        log.warning("%s", result.stats.truncated)
    if not result.metrics and result.baseline is None:
        raise SystemExit(
            f"{args.log}: no frame with ground truth and score maps found in {result.stats.messages} messages; "
            "expected channels umad/<graph>/<op>/{truth,frame,map,masks}"
        )
    index = write_report(result, args.out, args.log, layout=args.layout)
    log.info(
        "%d configurations over %d frames in %.1f s; report: %s",
        len(result.metrics),
        result.stats.frames,
        result.seconds,
        index,
    )
    print(index)
    return 0
