"""`gridslam demo`: the full stack on the synthetic world (two laps, no download)."""

from __future__ import annotations

from services.cli.run import add_run_arguments, execute


def register(subparsers) -> None:
    parser = subparsers.add_parser("demo", help="run the full stack on the synthetic world (two laps, no download)")
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
