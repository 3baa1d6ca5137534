"""`umad generate synthetic OUT`: write the built-in synthetic driving benchmark (AnoVox generator layout).

OUT/normal/Scenario_<uuid>/ holds drives without anomalies (training data), OUT/anomalous/ drives with
one anomalous object on the road each (evaluation data). Same arguments, same bytes.

`--stress` writes the stress set instead (its own default seed and drive counts, never part of the
default benchmark): uneven weather coverage in the normal drives, an ego waiting 20-40 m before the
object under rarely seen light in the anomalous ones. `--stress-light` writes the light stress set:
the sun's cast shadows and lane glare, clear light in few normal drives and in every anomalous one.
`--stress-facades` writes the facades stress set: built-up streets with a row of thin poles by the
curb, the sun low and to the side on the facades; anomalous drives alternate night and sunset.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import time
from pathlib import Path

from umad_common.commands.checks import InputError, writable_output
from umad_common.commands.common import add_frames_argument, add_seed_argument

log = logging.getLogger("umad.generate")


def parse_size(text: str) -> tuple[int, int]:
    """'384x256' -> (384, 256)."""
    match = re.fullmatch(r"(\d+)[xX](\d+)", text.strip())
    if not match:
        raise argparse.ArgumentTypeError(f"size {text!r} must look like WxH, e.g. 384x256")
    width, height = int(match.group(1)), int(match.group(2))
    if width < 16 or height < 16 or width % 2 or height % 2:
        raise argparse.ArgumentTypeError(f"size {text!r}: width and height must be even and >= 16")
    return width, height


STRESS_HELP = (
    "write the stress set instead of the default benchmark (defaults: --normal 12 --anomalous 8 "
    "--seed 30). Normal drives cover the presets unevenly, per 12 drives: cloudy 5, fog 3, rain 2, "
    "dusk 1, night 1, clear_noon 0 (the cycle cloudy fog rain dusk cloudy fog rain cloudy fog cloudy "
    "night cloudy). Anomalous drives cycle clear_noon dusk fog night clear_noon dusk rain cloudy; in "
    "each the ego brakes early, stops 20-40 m before the object and waits there to the end"
)
STRESS_LIGHT_HELP = (
    "write the light stress set instead (defaults: --normal 16 --anomalous 8 --seed 43; choose on "
    "--seed 44, which umad eval never evaluates). The sun casts soft shadows of buildings, "
    "trees, poles and cars on the road and sidewalk, and lane paint glares toward a low sun, in every "
    "drive whose sun shows. Normal drives, per 16: cloudy 5, fog 3, rain 2, dusk 2, night 1, clear_noon 2, "
    "sunset 1 (clear light in 3). Anomalous drives alternate sunset and clear_noon, the sun ahead; in "
    "each the ego stops 20-40 m before the object and waits there to the end"
)

STRESS_FACADES_HELP = (
    "write the facades stress set instead (defaults: --normal 16 --anomalous 8 --seed 47; choose on "
    "--seed 48, which umad eval never evaluates). Every drive is built up (urban or suburban) with a "
    "row of bare thin poles 6-10 m apart along each sidewalk by the curb; the sun, casting shadows "
    "where it shows, stands 95-125 degrees to the side of the road where the drive ends, so a low sun "
    "lights the facades beside the road. Normal drives, per 16: cloudy 5, fog 3, rain 2, dusk 2, "
    "clear_noon 2, night 1, sunset 1. Anomalous drives alternate night and sunset; in each the ego "
    "stops 20-40 m before the object and waits there to the end"
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=Path, help="output folder (must not already hold normal/ or anomalous/ scenarios)")
    parser.add_argument(
        "--normal",
        type=int,
        default=None,
        help="number of normal drives (default 12: 2 per weather; --stress: 12; --stress-light, --stress-facades: 16)",
    )
    parser.add_argument(
        "--anomalous", type=int, default=None, help="number of drives with an anomaly (default 6; the stress sets: 8)"
    )
    add_frames_argument(parser, 200, help="frames per drive at 10 Hz (default 200)")
    add_seed_argument(
        parser,
        None,
        help="master seed; same seed, same bytes (default 0; --stress: 30; --stress-light: 43; --stress-facades: 47)",
    )
    parser.add_argument("--size", type=parse_size, default=(384, 256), help="camera image size WxH (default 384x256)")
    sets = parser.add_mutually_exclusive_group()
    sets.add_argument("--stress", action="store_true", help=STRESS_HELP)
    sets.add_argument("--stress-light", action="store_true", help=STRESS_LIGHT_HELP)
    sets.add_argument("--stress-facades", action="store_true", help=STRESS_FACADES_HELP)
    parser.add_argument("--preview", action="store_true", help="also write OUT/preview.png, a contact sheet")
    parser.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count() or 1,
        help="processes rendering scenarios at once (default: the machine's cores); the bytes do not depend on it",
    )


def run(args: argparse.Namespace) -> int:
    from umad_common.datasets.synthetic.generator import STRESS, STRESS_FACADES, STRESS_LIGHT

    chosen = ((args.stress, STRESS), (args.stress_light, STRESS_LIGHT), (args.stress_facades, STRESS_FACADES))
    stress = next((s for flag, s in chosen if flag), None)
    defaults = {
        "normal": 16 if stress in (STRESS_LIGHT, STRESS_FACADES) else 12,
        "anomalous": 6 if stress is None else 8,
        "seed": 0 if stress is None else stress.seed,
    }
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    for name, least in (("normal", 0), ("anomalous", 0), ("frames", 1), ("workers", 1)):
        if getattr(args, name) < least:
            raise InputError.of(f"--{name} {getattr(args, name)}", f"is below {least}", f"at least {least}")
    out: Path = writable_output(args.out, "OUT")
    for split in ("normal", "anomalous"):
        if (out / split).is_dir() and any((out / split).iterdir()):
            raise InputError.of(f"OUT {out}", f"{split}/ already holds scenarios", "an empty or new output folder")

    from tqdm import tqdm

    from umad_common.datasets.synthetic.generator import generate_benchmark, write_preview

    total = (args.normal + args.anomalous) * args.frames
    started = time.perf_counter()
    desc = "generate synthetic" if stress is None else f"generate {stress.name.replace('_', ' ')} set"
    with tqdm(total=total, unit="frame", desc=desc) as bar:
        roots = generate_benchmark(
            out,
            args.normal,
            args.anomalous,
            args.frames,
            args.seed,
            args.size,
            on_frame=bar.update,
            stress=stress,
            workers=args.workers,
        )
    seconds = time.perf_counter() - started
    log.info(
        "wrote %d scenarios (%d frames) to %s in %.1f s (%.0f ms/frame)",
        len(roots),
        total,
        out,
        seconds,
        1000 * seconds / max(total, 1),
    )
    if args.preview and roots:
        write_preview(roots, out / "preview.png")
        log.info("preview: %s", out / "preview.png")
    return 0
