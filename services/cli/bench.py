"""`gridslam bench NAME [ARGS]`: a benchmark of one part, printed as a Markdown table of medians."""

from __future__ import annotations

import argparse
import importlib

# Benchmark name → module with main(argv) -> int.
BENCHMARKS: dict[str, str] = {
    "source": "services.source.bench",
    "gridcells": "services.gridcells.bench",
    "egomotion": "services.egomotion.bench",
    "viewer": "services.viewer.bench",
    "pipeline": "services.pipeline.bench",
    "sharding": "services.pipeline.shard_bench",
    "load": "services.pipeline.load_bench",
    "loopclosure": "services.loopclosure.bench",
    "mapping": "services.expmap.bench",
    "geometry": "services.loopclosure.geometry_bench",
    "place-recognition": "services.benchmarks.place_recognition",
    "ros2": "services.ros.bench",
    "foxglove": "services.ros.foxglove_bench",
}


def register(subparsers) -> None:
    parser = subparsers.add_parser("bench", help="run a benchmark (medians and ratios as a Markdown table)")
    parser.add_argument("name", choices=sorted(BENCHMARKS), help="what to benchmark")
    parser.add_argument("bench_args", nargs=argparse.REMAINDER, help="arguments of that benchmark (see NAME --help)")
    parser.set_defaults(func=run)


def run(args) -> int:
    return importlib.import_module(BENCHMARKS[args.name]).main(args.bench_args)
