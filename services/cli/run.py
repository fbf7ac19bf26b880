"""`gridslam run`: the whole stack on any source, as separate local processes over Zenoh."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from services.common.config import load_config
from services.common.layout import add_map_reuse_arguments
from services.common.runtime import DEFAULT_ROUTER
from services.expmap.service import add_map_arguments
from services.pipeline.fleet import add_fleet_arguments
from services.loopclosure.service import add_place_recognition_argument
from services.ros.node import add_graph_arguments, graph_flags
from services.source.service import add_fov_argument
from services.source.spec import add_bag_arguments, add_world_arguments, bag_settings, parse_world_flags


def add_run_arguments(parser, *, source_required: bool) -> None:
    parser.add_argument("--source", required=source_required,
                        help="kitti:PATH, stereo:PATH, images:PATH, video:FILE, camera:N, synthetic:SEED, rosbag:PATH or "
                             "ros2:TOPIC")
    parser.add_argument("--egomotion", choices=["scanline", "stereo", "mono", "passthrough"], help="ego-motion estimator")
    parser.add_argument("--egomotion-instances", type=int, metavar="N",
                        help="ego-motion processes sharing the frames (default 1; docs/pipeline.md)")
    parser.add_argument("--integrator", choices=["grid", "deadreckoning"], help="path integrator (default grid)")
    parser.add_argument("--decoder", choices=["paper", "fft", "subpixel", "calibrated"], help="lattice flow decoder (default calibrated)")
    parser.add_argument("--modules", type=int, help="grid modules (default 1; more need --decoder calibrated)")
    parser.add_argument("--heading", choices=["sum", "ring"], help="heading model: summed yaw (default) or a ring attractor")
    parser.add_argument("--preset", help="dataset preset: synthetic, campus, nubot, kitti, stlucia, or a preset file "
                                         "(base preset and per-service tables, docs/sources.md)")
    parser.add_argument("--calibration", type=Path, help="calibration TOML file for the source")
    add_fov_argument(parser)
    parser.add_argument("--camera-height", type=float, metavar="M",
                        help="camera height above the ground, m: a metric scale for the mono estimator (ground plane)")
    parser.add_argument("-c", "--config", type=Path, help="gridslam TOML config file for every service")
    parser.add_argument("--out", type=Path, help="results folder (default results/<timestamp>/ with a latest link)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier run in --out (a folder that holds one is refused otherwise)")
    parser.add_argument("--n-frames", type=int, help="process only this many frames")
    parser.add_argument("--start", type=int, help="first frame index")
    parser.add_argument("--step", type=step_value, action="append", metavar="N|odometry|lattice",
                        help="a number: take every N-th frame; odometry or lattice: where the grid cells' step length "
                             "comes from (default odometry); may be given twice")
    parser.add_argument("-l", "--listen", help=f"the run's router endpoint (default {DEFAULT_ROUTER})")
    parser.add_argument("-e", "--connect", metavar="ENDPOINT",
                        help="use the router at ENDPOINT instead of starting one (e.g. several robots on one network)")
    parser.add_argument("--robot", help="robot name (default robot0)")
    parser.add_argument("--no-mapping", dest="mapping", action="store_false", default=None,
                        help="skip loop closure and the experience map")
    add_map_arguments(parser)
    add_place_recognition_argument(parser)
    add_map_reuse_arguments(parser)
    parser.add_argument("--view", nargs="?", const="127.0.0.1:8080", metavar="HOST:PORT",
                        help="also serve the live viewer (default 127.0.0.1:8080); a run that ends by itself is "
                             "served on until Ctrl-C")
    add_world_arguments(parser)
    parser.add_argument("--foxglove", nargs="?", const=8765, type=int, metavar="PORT",
                        help="also serve the run live to Foxglove, ws://127.0.0.1:PORT (default 8765; extra `foxglove`); "
                             "a run that ends by itself is served on until Ctrl-C")
    parser.add_argument("--ros2", action="store_true", default=None,
                        help="also run the ros2 service: the run as the node gridslam of a ROS 2 graph over Zenoh "
                             "(rmw_zenoh; docs/ecosystem.md)")
    add_graph_arguments(parser)
    parser.add_argument("--no-mcap", dest="mcap", action="store_false", default=None,
                        help="do not write run.mcap (nor keep the camera images for it)")
    add_bag_arguments(parser)
    add_fleet_arguments(parser)


def step_value(text: str) -> int | str:
    """`--step`: a frame stride (a positive integer) or the grid cells' step source."""
    if text in ("odometry", "lattice"):
        return text
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, odometry or lattice, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, odometry or lattice, got {text!r}")
    return value


def register(subparsers) -> None:
    parser = subparsers.add_parser("run", help="run the whole stack on a dataset, camera or the synthetic world")
    add_run_arguments(parser, source_required=True)
    parser.set_defaults(func=run)


class Progress:
    """A progress line in frames with the rate: redrawn in place on a terminal, every 10 % otherwise."""

    def __init__(self, stream=sys.stderr):
        self.stream = stream
        self.started = time.monotonic()
        self.shown = -1

    def __call__(self, done: int, total: int | None) -> None:
        rate = done / max(time.monotonic() - self.started, 1e-9)
        if total:
            filled = int(30 * done / total)
            line = f"[{'#' * filled}{'.' * (30 - filled)}] {done}/{total} frames {rate:5.1f} frames/s"
            tenth = 10 * done // total
        else:
            line, tenth = f"{done} frames {rate:5.1f} frames/s", done // 100
        if self.stream.isatty():
            self.stream.write("\r" + line)
            self.stream.flush()
        elif tenth != self.shown:
            self.shown = tenth
            print(line, file=self.stream, flush=True)

    def close(self) -> None:
        if self.stream.isatty():
            self.stream.write("\n")


def run_flags(args) -> dict:
    """The RunConfig fields the flags set (None: not given). `--step` given a number is the
    frame stride, given odometry or lattice the grid cells' step source."""
    steps = args.step or []
    strides = [value for value in steps if isinstance(value, int)]
    sources = [value for value in steps if isinstance(value, str)]
    return {"source": args.source, "egomotion": args.egomotion, "egomotion_instances": args.egomotion_instances,
            "integrator": args.integrator, "decoder": args.decoder, "step_source": sources[-1] if sources else None,
            "modules": args.modules, "heading": args.heading,
            "preset": args.preset, "calibration": args.calibration, "fov": args.fov, "camera_height": args.camera_height, "config_file": args.config, "n_frames": args.n_frames,
            "start": args.start, "step": strides[-1] if strides else None, "listen": args.listen, "connect": args.connect,
            "robot": args.robot, "mapping": args.mapping, "view": args.view, "closure": args.closure,
            "map_optimizer": args.map_optimizer, "place_recognition": args.place_recognition,
            "map": args.map, "localize": args.localize, "world": parse_world_flags(args.world, args.laps) or None,
            "mcap": args.mcap, "foxglove": args.foxglove, "ros2": args.ros2, **graph_flags(args), **bag_settings(args)}


def execute(args, **defaults) -> int:
    """Build the RunConfig from defaults < config file [run] < flags, run it, print the summary."""
    from services.evaluation.results import format_table
    from services.pipeline.report import summary_rows
    from services.pipeline.runner import RunConfig, run_pipeline

    config = load_config(RunConfig, "run", defaults=defaults, config_file=args.config, overrides=run_flags(args))
    progress = Progress()
    if args.fleet:
        from services.pipeline.fleet import run_fleet_command
        try:
            return run_fleet_command(args, config, progress=progress)
        finally:
            progress.close()
    try:
        result = run_pipeline(config, args.out, progress=progress, overwrite=args.overwrite, serve=True,
                              announce=lambda line: print(line, file=sys.stderr, flush=True))
    finally:
        progress.close()
    try:
        print(format_table(summary_rows(result.metrics)))
        print(f"results: {result.folder}")
        if result.serving is not None:   # --view, --foxglove: time to connect to the finished run
            addresses = ", ".join(f"{name} {address}" for name, address in result.serving.addresses.items())
            print(f"the run has finished; serving it until Ctrl-C: {addresses}", flush=True)
            result.serving.wait()
    finally:
        if result.serving is not None:
            result.serving.close()
    return 0


def run(args) -> int:
    return execute(args)
