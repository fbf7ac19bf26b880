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


# --fleet: robots a and b drive one lap each of the two-lap corridor, b from the far side of the
# loop (frame 187), so each comes to places the other saw (docs/fleet.md).
FLEET_STARTS, FLEET_FRAMES = [0, 187], 374


def run(args) -> int:
    if args.fleet and not args.robot_start:
        args.robot_start = FLEET_STARTS
    fleet = {"n_frames": FLEET_FRAMES} if args.fleet else {}
    return execute(args, source="synthetic:0", preset="synthetic", **fleet)
