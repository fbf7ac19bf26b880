"""`gridslam service NAME [flags]`: run one service as this process."""

from __future__ import annotations

import argparse
import importlib
import logging
import os

from services.common.config import SERVICE_MODULES as SERVICES   # name → adapter: add_arguments(parser), main(runtime, args)
from services.common.runtime import add_runtime_flags, runtime_from_args
from services.common.settings import CommandParser, add_flag, renamed_flags


def register(subparsers) -> None:
    parser = subparsers.add_parser("service", help="run one service (source, egomotion, gridcells, ...)",
                                   description="Run one service; `gridslam service NAME --help` lists its flags.")
    parser.add_argument("name", choices=list(SERVICES), metavar="NAME", help=", ".join(SERVICES))
    parser.add_argument("service_args", nargs=argparse.REMAINDER, help="flags of that service")
    parser.set_defaults(func=run)


def service_parser(name: str):
    """The parser of one service's flags: the shared runtime flags plus its own; and its main()."""
    from services.common.service import ServiceParams

    module = importlib.import_module(SERVICES[name])
    parser = CommandParser(prog=f"gridslam service {name}", description=module.__doc__.strip().splitlines()[0])
    add_runtime_flags(parser)
    add_flag(parser, ServiceParams, "instance")
    module.add_arguments(parser)
    return parser, module.main


def service_defaults(name: str, environ=None) -> dict[str, str | None]:
    """The flags' defaults a service takes from the environment. A preset picks the config files
    a service's settings are read from, so it cannot be one of them: it comes from --preset, else
    GRIDSLAM_<SERVICE>_PRESET (containers)."""
    return {"preset": (os.environ if environ is None else environ).get(f"GRIDSLAM_{name.upper()}_PRESET")}


def run(args) -> int:
    parser, service_main = service_parser(args.name)
    parser.set_defaults(**service_defaults(args.name))
    service_args = parser.parse_args(args.service_args)
    for note in renamed_flags(service_args):
        logging.getLogger("gridslam").warning("%s", note)
    return service_main(runtime_from_args(service_args), service_args)
