"""`gridslam service NAME`: run one service as this process."""

from __future__ import annotations

import importlib

from services.common.runtime import add_runtime_flags, runtime_from_args

# Service name → adapter module; each exposes add_arguments(parser) and main(runtime, args) -> int.
SERVICES: dict[str, str] = {
    "gridcells": "services.gridcells.service",
}


def register(subparsers) -> None:
    parser = subparsers.add_parser("service", help="run one service (source, egomotion, gridcells, ...)")
    names = parser.add_subparsers(dest="service", metavar="NAME", required=True)
    for name, module_name in SERVICES.items():
        module = importlib.import_module(module_name)
        service_parser = names.add_parser(name, help=module.__doc__.strip().splitlines()[0])
        add_runtime_flags(service_parser)
        service_parser.add_argument("--instance", help="instance name in the health key (default host-pid)")
        module.add_arguments(service_parser)
        service_parser.set_defaults(func=run, service_main=module.main)


def run(args) -> int:
    return args.service_main(runtime_from_args(args), args)
