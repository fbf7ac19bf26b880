"""`gridslam bench NAME [ARGS]`: a benchmark of one part, printed as a Markdown table of medians."""

from __future__ import annotations

import argparse
import importlib

# Benchmark name → module with main(argv) -> int.
BENCHMARKS: dict[str, str] = {
    "source": "services.benchmarks.source",
    "gridcells": "services.benchmarks.gridcells",
    "egomotion": "services.benchmarks.egomotion",
    "viewer": "services.benchmarks.viewer",
    "pipeline": "services.benchmarks.pipeline",
    "sharding": "services.benchmarks.sharding",
    "load": "services.benchmarks.load",
    "loopclosure": "services.benchmarks.loopclosure",
    "mapping": "services.benchmarks.mapping",
    "geometry": "services.benchmarks.geometry",
    "place-recognition": "services.benchmarks.place_recognition",
    "ros2": "services.benchmarks.ros2",
    "foxglove": "services.benchmarks.foxglove",
}


def register(subparsers) -> None:
    parser = subparsers.add_parser("bench", help="run a benchmark (medians and ratios as a Markdown table)")
    parser.add_argument("name", choices=sorted(BENCHMARKS), help="what to benchmark")
    parser.add_argument("bench_args", nargs=argparse.REMAINDER, help="arguments of that benchmark (see NAME --help)")
    parser.set_defaults(func=run)


def run(args) -> int:
    return importlib.import_module(BENCHMARKS[args.name]).main(args.bench_args)
