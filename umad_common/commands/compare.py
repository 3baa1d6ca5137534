"""`umad compare RUN_A RUN_B [--out DIR]`: two evaluations side by side, B's changes marked."""

from __future__ import annotations

import argparse
from pathlib import Path

from umad_common.commands.checks import evaluation_run, writable_output
from umad_common.commands.common import add_out_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_a", type=Path, help="evaluation folder (or its results.json): the reference A")
    parser.add_argument("run_b", type=Path, help="evaluation folder (or its results.json): B, compared with A")
    add_out_argument(
        parser, help="write compare.md and compare.html here (default: print the Markdown)", required=False
    )


def run(args: argparse.Namespace) -> int:
    evaluation_run(args.run_a, "RUN_A")
    evaluation_run(args.run_b, "RUN_B")
    if args.out is not None:
        writable_output(args.out, "--out")

    from umad_common.viz.compare import compare_page, load_results
    from umad_common.viz.pages import render_page, write_page

    page = compare_page(load_results(args.run_a), load_results(args.run_b), str(args.run_a), str(args.run_b))
    if args.out is None:
        print(render_page(page, "md"))
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    markdown, html = write_page(page, args.out, "compare")
    print(f"{page.headline}\ncomparison: {markdown} (and {html})")
    return 0
