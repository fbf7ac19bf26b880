"""`gridslam odometry --source SPEC --estimator NAME`: run a frame source through an ego-motion
estimator offline (one process, no Zenoh), write the dead-reckoned trajectory, ground truth,
metrics and plots, and print a Metric | Value | Unit table (docs/egomotion.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.common.run_settings import RunOutputParams, RunParams
from services.common.settings import add_field_flag, add_flag, add_renamed_flag
from services.egomotion import EgomotionConfig
from services.offline.odometry import run_offline, summary_rows
from services.evaluation.results import format_table
from services.source.service import SourceConfig
from services.source.spec import add_bag_arguments, add_world_arguments, bag_settings, parse_world_flags


def positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number of frames >= 1, got {text!r}")
    return value


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "odometry",
        help="run a source through an ego-motion estimator offline and score it",
        description="Run a frame source through an ego-motion estimator in one process; write egomotion.tum and "
        "egomotion.kitti.txt (dead-reckoned), groundtruth.tum when known, increments.csv, metrics.json, config.json "
        "and trajectory.png; print a metric table.",
    )
    add_flag(parser, RunParams, "source", required=True, metavar="SPEC")
    add_field_flag(parser, EgomotionConfig, "estimator", choices=None, metavar="NAME")   # a bad name: resolve_estimator's one line
    add_flag(parser, RunParams, "preset", metavar="NAME|FILE")
    parser.add_argument("--config", type=Path, metavar="FILE", help="config file whose [egomotion] table (or a file of that table's shape) overrides the preset "
                             "(docs/egomotion.md)")
    add_flag(parser, RunParams, "calibration", metavar="FILE")
    add_flag(parser, RunParams, "start", metavar="K", standalone=True)
    add_field_flag(parser, SourceConfig, "stop", metavar="K")
    add_flag(parser, RunParams, "step", flag="--stride", metavar="N", standalone=True)
    add_renamed_flag(parser, "--step", "--stride", dest="step", type=int)
    add_flag(parser, RunParams, "n_frames", metavar="N", standalone=True)
    parser.add_argument("--reference", type=Path, metavar="FILE",
                        help="reference to score against, row k = frame k: TUM, KITTI poses, or a CSV of increments "
                        "(forward,left,yaw or LIBVISO2's table)")
    parser.add_argument("--shard-block", type=positive, metavar="N",
                        help="run the estimator in blocks of N frames as the egomotion service does (the increments of "
                             "a pipeline run, whatever its number of egomotion instances; docs/pipeline.md)")
    add_flag(parser, RunOutputParams, "out", metavar="DIR")
    add_world_arguments(parser)
    add_bag_arguments(parser)
    parser.set_defaults(func=run)


def run(args) -> int:
    result, folder = run_offline(
        args.source,
        estimator=args.estimator,
        preset=args.preset,
        config_file=args.config,
        calibration=args.calibration,
        start=args.start,
        stop=args.stop,
        step=args.step,
        n_frames=args.n_frames,
        reference=args.reference,
        out=args.out,
        world=parse_world_flags(args.world, args.laps),
        topics=bag_settings(args),
        shard_block=args.shard_block,
    )
    print(format_table(summary_rows(result)))
    print(f"results: {folder}")
    return 0
