"""The `gridslam` command line: one parser, one module per command (STYLE.md, evo's cli/).

Each command module exposes ``register(subparsers)`` and ``run(args) -> int``. Known errors
(GridslamError) become one line on stderr and exit code 1; unknown ones keep their traceback.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import logging
import sys

from services.common.environment import pin_blas_kernel
from services.common.errors import GridslamError
from services.common.settings import CommandParser, renamed_flags

# Command modules under services/cli/, in the order `gridslam --help` lists them.
COMMANDS: tuple[str, ...] = ("demo", "run", "router", "service", "echo", "health", "schemas", "bench", "integrate", "simulate", "calibrate", "odometry", "map", "world", "export", "vocabulary")


def version() -> str:
    """The installed gridslam's version (pyproject.toml's, as installed)."""
    try:
        return importlib.metadata.version("gridslam")
    except importlib.metadata.PackageNotFoundError:   # run from a checkout that was never installed
        return "unknown (not installed)"


def build_parser():
    parser = CommandParser(
        prog="gridslam",
        description="Bio-inspired visual odometry and SLAM over Zenoh: grid-cell path integration and RatSLAM mapping.",
    )
    parser.add_argument("--version", action="version", version=f"gridslam {version()}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    verbosity.add_argument("-q", "--quiet", action="store_true", help="only errors")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        importlib.import_module(f"services.cli.{name}").register(subparsers)
    return parser


def configure_logging(verbose: int, quiet: bool) -> None:
    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    pin_blas_kernel()   # before build_parser imports the commands, and with them numpy
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    for note in renamed_flags(args):
        logging.getLogger("gridslam").warning("%s", note)
    try:
        return int(args.func(args) or 0)
    except GridslamError as error:
        print(f"gridslam {args.command}: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
