"""`gridslam demo`: the full stack on the synthetic world (two laps, no download)."""

from __future__ import annotations

import argparse
import textwrap

from services.cli.run import HELP_WIDTH, add_run_arguments, execute, run_epilog


def register(subparsers) -> None:
    parser = subparsers.add_parser("demo", help="run the full stack on the synthetic world (two laps, no download)",
                                   description=textwrap.fill(
                                       "`gridslam run` on the synthetic world: two laps of a 12 m × 8 m corridor loop, "
                                       "stereo, no download (--source synthetic:0 --preset synthetic unless given).",
                                       HELP_WIDTH),
                                   epilog=run_epilog("demo"), formatter_class=argparse.RawDescriptionHelpFormatter)
    add_run_arguments(parser, source_required=False)
    parser.set_defaults(func=run)


def run(args) -> int:
    return execute(args, source="synthetic:0", preset="synthetic")
