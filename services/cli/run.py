"""`gridslam run`: the whole stack on any source, as separate local processes over Zenoh."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import textwrap
import time

from services.common.config import has_named_preset, load_config, preset_services, preset_values, presets
from services.common.layout import add_map_reuse_arguments
from services.common.run_settings import FOXGLOVE_PORT, VIEW_ADDRESS, RunOutputParams, RunParams
from services.common.settings import add_flag, note_renamed
from services.common.stages import STEP_SOURCES, GridStageParams
from services.expmap.service import add_map_arguments
from services.pipeline.fleet import add_fleet_arguments
from services.loopclosure.service import add_place_recognition_argument
from services.ros2wire.graph_settings import add_graph_arguments, graph_flags
from services.source.calibration import OPTIONAL_KEYS, REQUIRED_KEYS
from services.source.service import add_fov_argument
from services.source.spec import add_bag_arguments, add_world_arguments, bag_settings, parse_world_flags


HELP_WIDTH = 100   # --help's closing text is wrapped here (argparse keeps its lines as they are)
ESTIMATOR_NEEDS = ("stereo needs a stereo pair and its calibration (baseline); mono needs camera intrinsics (for "
                   "an image folder, video or camera without a calibration a pinhole of --fov degrees is assumed); "
                   "passthrough needs odometry or ground truth in the frames (the synthetic world, a ROS bag's "
                   "--odom-topic); scanline needs nothing")


def preset_estimators() -> dict[str, str | None]:
    """Every shipped preset (of any service) → the estimator its egomotion table names (None:
    it has none, the default applies)."""
    names = sorted({name for service in preset_services() for name in presets(service)})
    return {name: preset_values("egomotion", name).get("estimator") if has_named_preset("egomotion", name) else None
            for name in names}


def describe_presets() -> str:
    """The shipped presets and, for each, its estimator or which services it covers."""
    parts = []
    for name, estimator in preset_estimators().items():
        covers = [service for service in preset_services() if has_named_preset(service, name)]
        parts.append(f"{name} ({estimator})" if estimator else f"{name} ({', '.join(covers)} only)")
    return ", ".join(parts)


def run_epilog(command: str) -> str:
    """--help's closing text: the defaults that depend on the input, the calibration file's keys,
    the presets, examples and the renamed flags."""
    if command == "demo":
        examples = ["gridslam demo", "gridslam demo --view", "gridslam demo --source synthetic:1 --out results/seed1",
                    "gridslam demo --preset campus --n-frames 2000 --foxglove"]
    else:
        examples = ["gridslam run --source stereo:../shared/data/nubot_scene1 --preset nubot",
                    "gridslam run --source kitti:../shared/data/kitti06_clip --preset kitti --n-frames 200",
                    "gridslam run --source images:../shared/data/rtabmap_samples/images --fov 65",
                    "gridslam run --source video:stlucia.avi --preset stlucia --stride 2",
                    "gridslam run --source synthetic:0 --preset campus --view",
                    "gridslam run --source rosbag:BAG --image-topic /cam/image_raw --odom-topic /odom --egomotion passthrough",
                    "gridslam run --source stereo:../shared/data/nubot_scene1 --preset nubot --egomotion-instances 2",
                    "gridslam run --source synthetic:0 --preset synthetic --map results/earlier --localize"]
    paragraphs = [
        "estimator: when --egomotion names none, the preset's, else scanline; " + ESTIMATOR_NEEDS + ".",
        f"presets: {describe_presets()}; or a preset file (a base preset and per-service tables, docs/sources.md).",
        f"calibration file (--calibration FILE, TOML): {', '.join(REQUIRED_KEYS)} in pixels (required); "
        f"{', '.join(OPTIONAL_KEYS)} (optional: baseline in metres for a stereo pair, 0 or absent: monocular; "
        "width and height are checked against the images).",
        "settings come from defaults < --preset < --config FILE ([run] and one table per service) < GRIDSLAM_<SECTION>_<KEY> "
        "environment variables < flags.",
        "renamed flags (the old spellings still work, with a note): --step N is --stride N; "
        "--step odometry|lattice is --step-source odometry|lattice.",
    ]
    return "\n".join([*(textwrap.fill(text, HELP_WIDTH, subsequent_indent="  ") for text in paragraphs), "", "examples:",
                      *(f"  {line}" for line in examples)])


def add_run_arguments(parser, *, source_required: bool) -> None:
    """The flags of `gridslam run` and `demo`, in groups (their defaults: None, "not given")."""
    given = parser.add_argument_group("input")
    add_flag(given, RunParams, "source", required=source_required, metavar="SPEC",
             shown_default=None if source_required else "synthetic:0")
    add_flag(given, RunParams, "preset", metavar="NAME|FILE", shown_default=None if source_required else "synthetic")
    add_flag(given, RunParams, "calibration", metavar="FILE")
    add_fov_argument(given)
    add_flag(given, RunParams, "camera_height", metavar="M")
    add_flag(given, RunParams, "config_file", flag=("-c", "--config"), dest="config", metavar="FILE")
    add_flag(given, RunParams, "start", metavar="K")
    add_flag(given, RunParams, "n_frames", metavar="N")
    add_flag(given, RunParams, "step", flag="--stride", dest="stride", metavar="N")
    given.add_argument("--step", type=old_step_value, action=OldStep, help=argparse.SUPPRESS)

    stages = parser.add_argument_group("stages")
    add_flag(stages, RunParams, "egomotion")
    add_flag(stages, RunParams, "egomotion_instances", metavar="N")
    for name in ("integrator", "decoder"):
        add_flag(stages, GridStageParams, name)
    add_flag(stages, GridStageParams, "step", flag="--step-source", dest="step_source")
    add_flag(stages, GridStageParams, "modules", metavar="N")
    add_flag(stages, GridStageParams, "heading")
    add_flag(stages, RunParams, "mapping", flag="--no-mapping")

    mapping = parser.add_argument_group("mapping")
    add_map_arguments(mapping)
    recognition = parser.add_argument_group("place recognition")
    add_place_recognition_argument(recognition)
    reuse = parser.add_argument_group("map reuse")
    add_map_reuse_arguments(reuse)

    outputs = parser.add_argument_group("outputs")
    add_flag(outputs, RunOutputParams, "out", metavar="DIR")
    add_flag(outputs, RunOutputParams, "overwrite", default=False)
    add_flag(outputs, RunParams, "mcap", flag="--no-mcap")
    add_flag(outputs, RunParams, "view", nargs="?", const=VIEW_ADDRESS, metavar="HOST:PORT")
    add_flag(outputs, RunParams, "foxglove", nargs="?", const=FOXGLOVE_PORT, metavar="PORT")

    network = parser.add_argument_group("network")
    add_flag(network, RunParams, "listen", flag=("-l", "--listen"), metavar="ENDPOINT")
    add_flag(network, RunParams, "connect", flag=("-e", "--connect"), metavar="ENDPOINT")
    add_flag(network, RunParams, "robot", metavar="NAME")

    ros2 = parser.add_argument_group("ROS 2", textwrap.fill("the run as a node of a ROS 2 graph over Zenoh "
                                                            "(docs/ecosystem.md); the graph settings also apply to a "
                                                            "ros2: source", HELP_WIDTH - 4))
    add_flag(ros2, RunParams, "ros2")
    add_graph_arguments(ros2)

    bag = parser.add_argument_group("ROS bag", "topics of --source rosbag:PATH (and ros2:TOPIC)")
    add_bag_arguments(bag)

    world = parser.add_argument_group("synthetic world", textwrap.fill("settings of --source synthetic:SEED, over the "
                                                                       "preset's and the config file's [source] keys",
                                                                       HELP_WIDTH - 4))
    add_world_arguments(world)

    add_fleet_arguments(parser)


class OldStep(argparse.Action):
    """`--step`, once both the frame stride and the grid cells' step source: a number is read as
    --stride, odometry or lattice as --step-source (noted as renamed). The same meaning given
    twice with different values is refused: with one flag for two things that was easy to miss."""

    def __call__(self, parser, namespace, value, option_string=None):
        dest, new = ("step_source", "--step-source") if isinstance(value, str) else ("stride", "--stride")
        seen = getattr(namespace, "_old_step", {})
        if dest in seen and seen[dest] != value:
            parser.error(f"--step {seen[dest]} and --step {value}: give {new} once")
        namespace._old_step = {**seen, dest: value}
        setattr(namespace, dest, value)
        note_renamed(namespace, f"--step {value}", f"{new} {value}")


def old_step_value(text: str) -> int | str:
    """`--step` (the old spelling): a frame stride (a positive integer) or the grid cells' step source."""
    if text in STEP_SOURCES:
        return text
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer (--stride) or odometry or lattice (--step-source), "
                                         f"got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer (--stride), got {text!r}")
    return value


def register(subparsers) -> None:
    parser = subparsers.add_parser("run", help="run the whole stack on a dataset, camera or the synthetic world",
                                   description=textwrap.fill(
                                       "Run the whole stack (source, egomotion, gridcells, loopclosure, expmap) as local "
                                       "processes around a Zenoh router, evaluate what it published and write a results "
                                       "folder (docs/pipeline.md).", HELP_WIDTH),
                                   epilog=run_epilog("run"), formatter_class=argparse.RawDescriptionHelpFormatter)
    add_run_arguments(parser, source_required=True)
    parser.set_defaults(func=run)


class Progress:
    """A progress line in frames with the rate: redrawn in place on a terminal, every 10 % otherwise."""

    def __init__(self, stream=None):
        self.stream = stream if stream is not None else sys.stderr   # the stderr of now, not of the import
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


# RunConfig fields whose flag is not --FIELD-NAME (a bad value names the flag).
RUN_FLAGS = {"step": "--stride", "config_file": "--config", "mapping": "--no-mapping", "mcap": "--no-mcap",
             "world": "--world"}
RUN_DESTS = {"step": "stride", "config_file": "config"}   # RunParams fields whose flag's value is args.<other name>
# (window and stall_timeout have no flag: config file and environment only)


def run_flags(args) -> dict:
    """The RunConfig fields the flags set (None: not given)."""
    return {**{f.name: getattr(args, RUN_DESTS.get(f.name, f.name), None) for f in dataclasses.fields(RunParams)},
            "integrator": args.integrator, "decoder": args.decoder, "step_source": args.step_source,
            "modules": args.modules, "heading": args.heading, "fov": args.fov, "closure": args.closure,
            "map_optimizer": args.map_optimizer, "place_recognition": args.place_recognition,
            "map": args.map, "localize": args.localize, "world": parse_world_flags(args.world, args.laps) or None,
            **graph_flags(args), **bag_settings(args)}


def execute(args, **defaults) -> int:
    """Build the RunConfig from defaults < config file [run] < flags, run it, print the summary."""
    from services.evaluation.results import format_table
    from services.pipeline.report import summary_rows
    from services.pipeline.runner import RunConfig, run_pipeline

    config = load_config(RunConfig, "run", defaults=defaults, config_file=args.config, overrides=run_flags(args),
                         flags=RUN_FLAGS)
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
