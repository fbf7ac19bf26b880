"""`gridslam demo`: the full stack on the synthetic world (two laps, no download)."""

from __future__ import annotations

from services.cli.run import add_run_arguments, execute


def register(subparsers) -> None:
    parser = subparsers.add_parser("demo", help="run the full stack on the synthetic world (two laps, no download)")
    add_run_arguments(parser, source_required=False)
    parser.set_defaults(func=run)


def run(args) -> int:
    return execute(args, source="synthetic:0", preset="synthetic")
