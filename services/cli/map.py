"""`gridslam map`: the experience map offline.

- `map export STORE`: rebuild a persisted map from its log and write the graph (JSON) and the
  corrected per-frame trajectory (TUM).
- `map build`: view templates, loop closures and the experience map over an image folder and
  a motion file, in one process (the evidence of docs/mapping.md).
- `map sweep`: `map build` over several match thresholds and tolerances, as a Markdown table.
- `map route --map DIR --from X,Y --to X,Y`: the shortest route over a saved map (route.py).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.common.config import load_config, presets
from services.common.errors import ConfigError
from services.common.settings import REQUIRED, add_field_flag, add_flag, setting
from services.common.stages import INTEGRATORS
from services.evaluation.results import format_table
from services.expmap.service import add_map_arguments
from services.loopclosure.service import LoopClosureConfig, add_place_recognition_argument


def register(subparsers) -> None:
    parser = subparsers.add_parser("map", help="export a persisted experience map; build one offline from images and odometry")
    commands = parser.add_subparsers(dest="map_command", metavar="SUBCOMMAND", required=True)

    route = commands.add_parser("route", help="the shortest route over a saved map's experiences between two points")
    add_flag(route, RouteParams, "map", required=True, metavar="DIR", standalone=True)
    add_flag(route, RouteParams, "start", flag="--from", required=True, metavar="X,Y", type=point, standalone=True)
    add_flag(route, RouteParams, "goal", flag="--to", required=True, metavar="X,Y", type=point, standalone=True)
    add_flag(route, RouteParams, "out", metavar="FILE", standalone=True)
    add_flag(route, RouteParams, "reference", metavar="TUM", standalone=True)
    route.set_defaults(func=run_route)

    export = commands.add_parser("export", help="rebuild a map from its log; write the graph (JSON) and the corrected trajectory (TUM)")
    export.add_argument("store", type=Path, help="the map log (experience_map.log of a run)")
    for name in ("graph", "tum", "reference", "plot"):
        add_flag(export, ExportParams, name, standalone=True)
    _add_params(export, "map parameters (default: those the log was written with; given ones must match it)")
    export.set_defaults(func=run_export)

    for name, help_text in (("build", "build a map offline from an image folder and a motion file"),
                            ("sweep", "build offline maps over several match thresholds and tolerances (Markdown table)")):
        command = commands.add_parser(name, help=help_text)
        images = command.add_mutually_exclusive_group(required=True)
        add_flag(images, BuildParams, "images", standalone=True)
        add_flag(images, BuildParams, "source", standalone=True)
        add_flag(command, BuildParams, "odometry", required=True, standalone=True)
        for setting_name in ("integrator", "noise_rot_deg", "noise_trans", "seed", "n_frames", "same_place_radius"):
            add_flag(command, BuildParams, setting_name, standalone=True)
        _add_params(command, "loopclosure, expmap and gridcells parameters")
        add_place_recognition_argument(command)
        if name == "build":
            add_map_arguments(command)
            add_field_flag(command, LoopClosureConfig, "match_threshold")   # over the preset's and the config file's
            add_field_flag(command, LoopClosureConfig, "tolerance")
            add_flag(command, BuildParams, "out", required=True, standalone=True)
            add_flag(command, BuildParams, "title", standalone=True)
            command.set_defaults(func=run_build)
        else:
            add_flag(command, SweepParams, "thresholds", standalone=True)
            add_flag(command, SweepParams, "tolerances", standalone=True)
            command.set_defaults(func=run_sweep)


@dataclass(frozen=True)
class RouteParams:
    """`gridslam map route`'s settings (command line only)."""

    map: Path = setting(REQUIRED, help="a results folder holding a map")
    start: tuple[float, float] = setting(REQUIRED, help="start, map frame, m")
    goal: tuple[float, float] = setting(REQUIRED, help="goal, map frame, m")
    out: Path | None = setting(None, help="write the route as TUM to FILE and as nav_msgs/Path to FILE with .mcap "
                                          "(extra `ros`)")
    reference: Path | None = setting(None, help="ground truth of the map's frames (groundtruth.tum of the run that made "
                                                "it): the route's length through the true places of its experiences")


@dataclass(frozen=True)
class ExportParams:
    """`gridslam map export`'s settings (command line only)."""

    graph: Path | None = setting(None, help="graph JSON to write (default: STORE with .graph.json)")
    tum: Path | None = setting(None, help="TUM trajectory to write (default: STORE with .tum)")
    reference: Path | None = setting(None, help="ground truth (TUM, e.g. groundtruth.tum of a run): print the "
                                                "odometry's and the corrected errors")
    plot: Path | None = setting(None, help="PNG of the odometry and corrected trajectories (and the reference)")


@dataclass(frozen=True)
class BuildParams:
    """`gridslam map build` and `sweep`'s settings (command line only; the services' own come
    from --preset and --config, and --match-threshold, --tolerance from loopclosure's)."""

    odometry: Path = setting(REQUIRED, help="motion file, one row per image (e.g. nubot_scene1/libviso2_egomotion.csv)")
    images: Path | None = setting(None, help="folder of images (e.g. nubot_scene1/left)")
    source: str | None = setting(None, help="a source spec, e.g. stereo:../shared/data/nubot_scene1 (stereo closures)")
    integrator: str = setting("deadreckoning", choices=INTEGRATORS,
                              help="how the motion is integrated (grid: the network, with the gridcells preset's speed)")
    noise_rot_deg: float = setting(0.0, ge=0.0, help="add Gaussian yaw noise per frame, degrees")
    noise_trans: float = setting(0.0, ge=0.0, help="add Gaussian translation noise, fraction of each step")
    seed: int = setting(0, ge=0, help="noise seed")
    n_frames: int | None = setting(None, ge=1, help="only the first N images")
    same_place_radius: float = setting(1.0, gt=0.0, help="a closure between frames whose odometric positions are "
                                                         "farther apart is counted as false (m)")
    out: Path | None = setting(None, help="folder for the results")
    title: str = setting("", help="title of the plots")


@dataclass(frozen=True)
class SweepParams:
    """`gridslam map sweep`'s settings beside BuildParams (command line only)."""

    thresholds: str = setting("0.05,0.06,0.07,0.08,0.1,0.12,0.13,0.14,0.15,0.2", help="comma-separated match thresholds")
    tolerances: str = setting("5,6", help="comma-separated consistency tolerances (frames)")


def _add_params(parser, what: str) -> None:
    parser.add_argument("--preset", help=f"{what}: a dataset preset (synthetic, nubot, kitti, stlucia)")
    parser.add_argument("-c", "--config", type=Path, help=f"{what}: a gridslam TOML config file ([expmap], [loopclosure], ...)")


def _config(model, section: str, args, overrides=None):
    return load_config(model, section, preset=args.preset, config_file=args.config, overrides=overrides)


def point(text: str) -> tuple[float, float]:
    """X,Y in metres (--from, --to)."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in metres, got {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise argparse.ArgumentTypeError(f"expected finite X,Y, got {text!r}")
    return x, y


def run_route(args) -> int:
    from services.common.layout import MAP_LOG
    from services.evaluation.trajectory import Trajectory, read_tum, write_tum
    from services.expmap.export import read_log
    from services.expmap.route import shortest_route

    map_log = read_log(args.map / MAP_LOG)
    experience_map = map_log.rebuild()
    route = shortest_route(experience_map.final_poses(), experience_map.links, args.start, args.goal)
    first, last = (route.experiences[0], route.experiences[-1]) if route.experiences else (None, None)
    print(format_table([("from experience", f"{first} ({args.start[0]:g}, {args.start[1]:g})", ""),
                        ("to experience", f"{last} ({args.goal[0]:g}, {args.goal[1]:g})", ""),
                        ("found", route.found, ""), ("experiences on the route", len(route.experiences), ""),
                        ("length", route.length, "m")]))
    if not route.found:
        raise ConfigError(f"{args.map}: no route: experiences {first} and {last} are in parts of the map no link joins")
    if args.reference is not None:
        true = true_places(map_log, experience_map, route.experiences, read_tum(args.reference))
        print(f"through the true places of its experiences (--reference): {np.hypot(*np.diff(true, axis=0).T).sum():.1f} m; "
              f"start and goal {np.hypot(*(true[-1] - true[0])):.1f} m apart")
    if args.out is not None:
        from services.ros.mcap_export import write_route_mcap

        poses = route.poses
        write_tum(args.out, Trajectory.from_planar(np.arange(len(poses), dtype=float), poses[:, 0], poses[:, 1], poses[:, 2]))
        print(f"route: {args.out}")
        mcap = args.out.with_suffix(".mcap")
        write_route_mcap(mcap, poses)
        print(f"route: {mcap}")
    return 0


def true_places(map_log, experience_map, experiences: list[int], reference) -> np.ndarray:
    """The true positions (N, 2) of experiences: where the reference puts the frames that made
    them (frames paired by stamp)."""
    stamp_of = {step.frame: round(step.stamp, 6) for step in map_log.steps}
    at_stamp = {round(stamp, 6): position[:2] for stamp, position in zip(reference.stamps, reference.positions)}
    missing = [e for e in experiences if stamp_of.get(experience_map.created[e]) not in at_stamp]
    if missing:
        raise ConfigError(f"the reference has no pose at the frame of experience {missing[0]} (frame "
                          f"{experience_map.created[missing[0]]}): give the ground truth of the run that made the map")
    return np.array([at_stamp[stamp_of[experience_map.created[e]]] for e in experiences])


def run_export(args) -> int:
    from services.evaluation.trajectory import read_tum
    from services.evaluation.plots import plot_trajectories
    from services.expmap.export import corrected_trajectory, errors_against, export_map, odometry_trajectory
    from services.expmap.service import ExpMapConfig

    params = _config(ExpMapConfig, "expmap", args).params() if (args.preset or args.config) else None
    graph = args.graph or args.store.with_suffix(".graph.json")
    tum = args.tum or args.store.with_suffix(".tum")
    result = export_map(args.store, graph, tum, params)
    summary = result.summary()
    print(format_table([("frames", summary["frames"], ""), ("experiences", summary["experiences"], ""),
                        ("links", summary["links"], ""), ("loop-closure links", summary["loop_closure_links"], ""),
                        ("sessions", summary["sessions"], ""),
                        ("parts of the graph", summary["parts"], "1: one connected map; more: sessions not joined"),
                        ("torn last record skipped", summary["torn_last_record"], "")]))
    if args.reference is not None:
        errors = errors_against(result.map_log, result.experience_map, read_tum(args.reference))
        print()
        print(f"position errors against {args.reference} (m; poses paired by stamp):")
        print(format_table([(f"{name}, {'as is' if kind == 'none' else 'SE(2)-aligned'}: {stat}", errors[name][kind][stat], "m")
                            for name in ("odometry", "corrected") for kind in ("none", "se2") for stat in ("mean", "max")]))
    if args.plot is not None:
        trajectories = {"groundtruth": read_tum(args.reference)} if args.reference is not None else {}
        trajectories |= {"odometry (map input)": odometry_trajectory(result.map_log.steps),
                         "corrected (final map)": corrected_trajectory(result.experience_map, result.map_log.steps)}
        result.files["plot"] = plot_trajectories(args.plot, trajectories, title=f"Experience map of {args.store}")
    for name, path in result.files.items():
        if path is not None:   # (a plot, without matplotlib)
            print(f"{name}: {path}")
    return 0


def _inputs(args):
    """Images, odometry and the three services' parameters of a build or sweep."""
    from services.offline.mapping import odometry_from_motion
    from services.expmap.service import ExpMapConfig
    from services.gridcells.config import GridCellsConfig
    from services.gridcells.integrator import auto_velocity_scale
    from services.gridcells.network import NetworkParams
    from services.loopclosure.service import LoopClosureConfig
    from services.source.datasets import ImageFolder
    from services.source.spec import load_preset, open_source

    if not (args.same_place_radius > 0 and math.isfinite(args.same_place_radius)):
        raise ConfigError(f"--same-place-radius must be a positive number of metres, got {args.same_place_radius}")
    overrides = {name: getattr(args, name, None) for name in ("match_threshold", "tolerance", "closure", "place_recognition")}
    loopclosure = _config(LoopClosureConfig, "loopclosure", args, overrides)
    expmap = _config(ExpMapConfig, "expmap", args, {"closure": getattr(args, "closure", None),
                                                    "optimizer": getattr(args, "map_optimizer", None)})
    gridcells = _config(GridCellsConfig, "gridcells", args)
    params = NetworkParams(n=gridcells.neurons)
    scale = (auto_velocity_scale(np.array([gridcells.typical_speed]), params) if gridcells.velocity_scale == "auto"
             else float(gridcells.velocity_scale))
    odometry = odometry_from_motion(args.odometry, args.integrator, gridcells.decoder, scale, args.noise_trans,
                                    args.noise_rot_deg, args.seed)
    # Closures are judged on the noiseless dead reckoning of the motion file.
    reference = odometry_from_motion(args.odometry) if (args.noise_trans or args.noise_rot_deg) else None
    source_preset = args.preset if args.preset in presets("source") else None
    if args.source:
        images = open_source(args.source, stop=args.n_frames, preset=source_preset)
    else:   # a mono folder; the source preset's calibration (if any) lets closures be measured
        camera = load_preset(source_preset)[0] if source_preset else None
        images = ImageFolder(args.images, stop=args.n_frames, grey=True, camera=camera)
    config = {"images": args.images, "source": args.source, "odometry": args.odometry, "integrator": args.integrator,
              "noise_trans": args.noise_trans, "noise_rot_deg": args.noise_rot_deg, "seed": args.seed,
              "same_place_radius": args.same_place_radius, "loopclosure": loopclosure.model_dump(mode="json"),
              "expmap": expmap.model_dump(mode="json"), "gridcells": gridcells.model_dump(mode="json") if args.integrator == "grid" else None}
    return images, odometry, reference, loopclosure, expmap, config


def run_build(args) -> int:
    from services.offline.mapping import build_map, write_build

    images, odometry, reference, loopclosure, expmap, config = _inputs(args)
    args.out.mkdir(parents=True, exist_ok=True)
    store = args.out / "experience_map.log"
    if store.exists():
        store.unlink()   # a build starts a new map (the log is the map's record, not an input)
    run = build_map(images, odometry, loopclosure.detector(), expmap.params(), store, reference)
    files = write_build(args.out, run, args.same_place_radius, config, args.title)
    summary = run.summary(args.same_place_radius)
    first = summary["first_confirmed"]
    print(format_table([
        ("frames", summary["frames"], ""), ("view templates", summary["view_templates"], ""),
        ("experiences", summary["experiences"], ""), ("links (loop closure)", f"{summary['links']} ({summary['loop_closure_links']})", ""),
        ("possible closures", summary["possible_closures"], ""),
        ("possible closures elsewhere", summary["possible_closures_elsewhere"], f"> {args.same_place_radius:g} m"),
        ("confirmed closures", summary["confirmed_closures"], ""),
        ("confirmed closures elsewhere", summary["confirmed_closures_elsewhere"], f"> {args.same_place_radius:g} m"),
        ("closures accepted / rejected / unmeasured by the map",
         f"{summary['closures_accepted']} / {summary['closures_rejected']} / {summary['closures_unmeasured']}", ""),
        ("first confirmed", f"frame {first['frame']} ↔ frame {first['matched_frame']}" if first else "-", ""),
        ("confirmed at frames", "{}..{}".format(*summary["confirmed_frames"]) if first else "-", ""),
        ("matched frames", ",".join(map(str, summary["matched_frames"])) or "-", ""),
        ("odometry end-to-start gap", summary["odometry_end_to_start_m"], "m"),
        ("corrected end-to-start gap", summary["corrected_end_to_start_m"], "m"),
    ] + [(f"{name.removesuffix('_m').replace('_', ' ')} ({stat}, SE(2))", value, "m") for name in ("odometry_error_vs_reference_m", "corrected_error_vs_reference_m")
         if name in summary for stat, value in summary[name].items() if stat != "rmse"]))
    print(f"results: {args.out} ({', '.join(sorted(p.name for p in files.values()))}, {store.name})")
    return 0


def run_sweep(args) -> int:
    from services.offline.mapping import sweep

    try:
        thresholds = [float(v) for v in args.thresholds.split(",") if v.strip()]
        tolerances = [int(v) for v in args.tolerances.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(f"--thresholds {args.thresholds!r} / --tolerances {args.tolerances!r}: comma-separated numbers expected") from None
    images, odometry, reference, loopclosure, expmap, _ = _inputs(args)
    images = list(images)   # read once, matched many times
    rows = sweep(images, odometry, loopclosure, expmap.params(), thresholds, tolerances, args.same_place_radius, reference)
    header = list(rows[0]) if rows else []
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join("---:" for _ in header) + "|")
    for row in rows:
        print("| " + " | ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in row.values()) + " |")
    return 0
