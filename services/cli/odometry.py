"""`gridslam odometry --source SPEC --estimator NAME`: run a frame source through an ego-motion
estimator offline (one process, no Zenoh), write the dead-reckoned trajectory, ground truth,
metrics and plots, and print a Metric | Value | Unit table (docs/egomotion.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.common.settings import add_renamed_flag
from services.egomotion import ESTIMATORS
from services.offline.odometry import run_offline, summary_rows
from services.evaluation.results import format_table
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
    parser.add_argument("--source", required=True, metavar="SPEC",
                        help="kitti:PATH, stereo:PATH, images:PATH, video:FILE, camera:N, synthetic:SEED or rosbag:PATH")
    parser.add_argument("--estimator", metavar="NAME", help=f"{', '.join(ESTIMATORS)} (default: the one the preset or config names, else scanline)")
    parser.add_argument("--preset", metavar="NAME", help="dataset preset for the source and the estimator (nubot, kitti, stlucia, synthetic, campus) or a preset file")
    parser.add_argument("--config", type=Path, metavar="FILE", help="config file whose [egomotion] table (or a file of that table's shape) overrides the preset "
                             "(docs/egomotion.md)")
    parser.add_argument("--calibration", type=Path, metavar="FILE", help="camera calibration file (docs/sources.md)")
    parser.add_argument("--start", type=int, default=0, help="first frame (default 0)")
    parser.add_argument("--stop", type=int, help="frame to stop before (default: the end)")
    parser.add_argument("--stride", dest="step", type=int, default=1, metavar="N", help="use every N-th frame (default 1)")
    add_renamed_flag(parser, "--step", "--stride", dest="step", type=int)
    parser.add_argument("--n-frames", type=int, metavar="N", help="process at most N frames")
    parser.add_argument("--reference", type=Path, metavar="FILE",
                        help="reference to score against, row k = frame k: TUM, KITTI poses, or a CSV of increments "
                        "(forward,left,yaw or LIBVISO2's table)")
    parser.add_argument("--shard-block", type=positive, metavar="N",
                        help="run the estimator in blocks of N frames as the egomotion service does (the increments of "
                             "a pipeline run, whatever its number of egomotion instances; docs/pipeline.md)")
    parser.add_argument("--out", type=Path, metavar="DIR", help="results folder (default: results/<timestamp>/, with results/latest)")
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
