"""`gridslam run --fleet` and `gridslam demo --fleet`: several robots on one Zenoh network and the
fleet map over them (docs/fleet.md).

Steps: a router, the fleetmap service, then one whole-stack run per robot (`a`, `b`, ...; each
its own process, services/pipeline/fleet_member.py, with its own results folder `<out>/<robot>/`),
robot k starting at its `--robot-start` frame, once the first robot has done its
`--robot-delay` frames; every robot's ground truth has the first robot's first frame as its
origin, so all are in robot a's frame, the fleet frame. When every robot has finished, the fleet
map is stopped and the fleet evaluated (`evaluate_fleet`): `fleet/<robot>.tum` (its frames placed
on the final fleet map), `fleet/<robot>.online.tum` (its fleet poses as published, from its join
on), `fleet/<robot>.groundtruth.tum`, and the `fleet` object of metrics.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import string
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from schemas import FleetPose, MapPose
from services.common import codec, health, topics
from services.common.config import preset_applies
from services.common.convert import heading_of
from services.common.errors import ConfigError
from services.common.geometry import compose
from services.common.layout import CONFIG, LOGS, MAP_LOG, METRICS
from services.common.runtime import RuntimeConfig, open_session
from services.evaluation import metrics as trajectory_metrics
from services.evaluation.results import results_dir, write_config, write_json
from services.evaluation.revisits import TRUE_CLOSURE_M, same_place
from services.evaluation.trajectory import Trajectory, read_tum, write_tum
from services.expmap.export import read_log
from services.fleetmap.store import read_fleet_log
from services.pipeline.fleet_member import PARKED
from services.pipeline.runner import (RunConfig, RunError, Serving, Supervisor, check_port_free,
                                      clear_previous_run, wait_port_open)
from services.ros.foxglove import check_available as check_foxglove_available

log = logging.getLogger(__name__)

FLEET = "fleet"                 # the results sub-folder of the fleet map
FLEET_LOG = "fleet_map.log"
MAX_ROBOTS = 26
MEET_RADIUS_M = 2.0             # a place another robot saw: within this of it ...
MEET_HEADING_RAD = math.radians(45)   # ... facing the same way (a forward camera sees the other wall otherwise)
DRAIN_S = 3.0                   # after the last robot: how long the fleet map may take to catch up, at most


def robot_names(count: int) -> list[str]:
    if not 1 <= count <= MAX_ROBOTS:
        raise ConfigError(f"--robots: 1 to {MAX_ROBOTS} robots, got {count}")
    return list(string.ascii_lowercase[:count])


def add_fleet_arguments(parser: argparse.ArgumentParser) -> None:
    """The fleet's flags of `gridslam run` and `gridslam demo`."""
    group = parser.add_argument_group("fleet (docs/fleet.md)")
    group.add_argument("--fleet", action="store_true", help="run several robots (a, b, ...) on one network and the fleet "
                                                            "map over them")
    group.add_argument("--robots", type=int, metavar="N", help="with --fleet: how many robots (default 2)")
    group.add_argument("--robot-start", type=int, action="append", metavar="FRAME",
                       help="with --fleet: the first frame of the next robot (repeatable, one per robot in order; "
                            "default: robot a at --start, the others spread along the route)")
    group.add_argument("--robot-delay", type=int, action="append", metavar="FRAMES",
                       help="with --fleet: start the next robot once robot a has done this many frames (repeatable; "
                            "default 0: all at once)")


def fleet_plan(args, config: RunConfig, total_frames: int | None) -> list[tuple[str, int, int]]:
    """(robot, first frame, delay in frames of robot a) for every robot of the fleet."""
    names = robot_names(args.robots or 2)
    starts = list(args.robot_start or [])
    delays = list(args.robot_delay or [])
    if len(starts) > len(names) or len(delays) > len(names):
        raise ConfigError(f"--robot-start / --robot-delay: at most one per robot ({len(names)} robots)")
    if any(s < 0 for s in starts) or any(d < 0 for d in delays):
        raise ConfigError("--robot-start and --robot-delay take frames ≥ 0")
    if len(starts) < len(names):   # the rest spread along the route
        span = total_frames or 1000
        starts += [config.start + (len(starts) + i) * span // len(names) for i in range(len(names) - len(starts))]
    delays += [0] * (len(names) - len(delays))
    return list(zip(names, starts, delays))


def robot_config(config: RunConfig, robot: str, start: int, origin: int, router: str) -> RunConfig:
    return config.model_copy(update={"robot": robot, "start": start, "origin": origin, "connect": router, "fleet": True,
                                     "view": None, "foxglove": None, "ros2": False})


class FleetRecorder:
    """The fleet map's poses of every robot (FleetPose), and each robot's map/pose count (progress)."""

    def __init__(self, runtime: RuntimeConfig):
        self.runtime = runtime
        self.lock = threading.Lock()
        self.poses: dict[str, dict[int, tuple[float, float, float, float, bool]]] = {}   # robot → seq → x, y, h, stamp, joined
        self.done: dict[str, set[int]] = {}   # robot → the frames its map has posed
        self.session = None
        self._subscribers = []

    def __enter__(self) -> FleetRecorder:
        self.session = open_session(self.runtime)
        self._subscribers.append(self.session.declare_subscriber(f"{topics.PREFIX}/{topics.FLEET}/*/pose", self._on_pose))
        self._subscribers.append(self.session.declare_subscriber(topics.key("*", "map/pose"), self._on_map_pose))
        return self

    def __exit__(self, *exc) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        if self.session is not None:
            self.session.close()

    def _on_pose(self, sample: zenoh.Sample) -> None:
        try:
            message = codec.decode(sample.payload.to_bytes(), FleetPose, str(sample.encoding))
        except codec.CodecError:
            return
        with self.lock:
            self.poses.setdefault(message.header.robot, {})[message.header.seq] = (
                message.pose.position.x, message.pose.position.y, heading_of(message.pose),
                message.header.stamp.to_seconds(), message.joined)

    def _on_map_pose(self, sample: zenoh.Sample) -> None:
        robot = str(sample.key_expr).split("/")[2]
        try:
            seq = codec.decode(sample.payload.to_bytes(), MapPose, str(sample.encoding)).header.seq
        except codec.CodecError:
            return
        with self.lock:   # a frame the source sent again (no acknowledgement in time) counts once
            self.done.setdefault(robot, set()).add(seq)

    def frames_done(self, robot: str) -> int:
        with self.lock:
            return len(self.done.get(robot, ()))

    def live(self) -> set[tuple[str, str, str]]:
        return set(health.live_services(self.session, timeout=1.0))


def observer_args(config: RunConfig, name: str, router: str, frame_robot: str) -> list[str]:
    """`gridslam service viewer|foxglove ... --fleet`: one server for the whole fleet, showing every
    robot in the fleet frame (and the first robot's own pipeline, in the viewer's other panels)."""
    args = ["service", name, "-e", router, "--robot", frame_robot, "--instance", name, "--fleet"]
    args += ["--http", config.view] if name == "viewer" else ["--port", str(config.foxglove)]
    if config.config_file is not None:
        args += ["--config", str(config.config_file)]
    return args


def run_fleet(config: RunConfig, plan: list[tuple[str, int, int]], out: Path | None = None, progress=None,
              overwrite: bool = False, announce=None, serve: bool = False) -> tuple[Path, dict, Serving | None]:
    """Run the fleet; its results folder, metrics, and (with `serve`, and a viewer or a Foxglove
    server: `--view`, `--foxglove`) the finished fleet's servers, still running until the caller's
    `Serving.wait()`."""
    if config.connect is None:
        check_port_free(config.listen)
    if config.foxglove is not None:   # fail now, in one line
        check_foxglove_available()
        if config.foxglove:
            check_port_free(f"tcp/127.0.0.1:{config.foxglove}")
    if config.map is not None:
        raise ConfigError("--fleet does not take --map (each robot starts a map of its own)")
    if not config.mapping:
        raise ConfigError("--fleet needs the map stage (drop --no-mapping)")
    folder = results_dir(out)
    clear_previous_run(folder / FLEET, overwrite)
    for robot, _, _ in plan:
        clear_previous_run(folder / robot, overwrite)
        if overwrite and (folder / robot / METRICS).exists():
            (folder / robot / METRICS).unlink()
    (folder / FLEET / LOGS).mkdir(parents=True, exist_ok=True)
    router = config.connect or config.listen
    origin = plan[0][1]
    write_config(folder / CONFIG, {**config.model_dump(mode="json"),
                                   "fleet_robots": [{"robot": r, "start": s, "delay": d} for r, s, d in plan]})
    supervisor = Supervisor(folder / FLEET / LOGS)
    names = [robot for robot, _, _ in plan]
    observers = (["viewer"] if config.view else []) + (["foxglove"] if config.foxglove is not None else [])
    kept: list[str] = []
    started = time.monotonic()
    try:
        if config.connect is None:
            child = supervisor.start("router", ["router", "--listen", config.listen])
            wait_port_open(config.listen, child.process)
        fleetmap_args = ["service", "fleetmap", "-e", router, "--instance", "fleetmap", "--store",
                         str(folder / FLEET / FLEET_LOG), "--frame-robot", names[0]]
        if config.config_file is not None:
            fleetmap_args += ["--config", str(config.config_file)]
        if config.preset and preset_applies("fleetmap", config.preset):
            fleetmap_args += ["--preset", config.preset]
        supervisor.start("fleetmap", fleetmap_args)
        with FleetRecorder(RuntimeConfig(connect=[router], robot=topics.FLEET)) as recorder:
            supervisor.wait_until("fleetmap", lambda: (topics.FLEET, "fleetmap", "fleetmap") in recorder.live(), "come up")
            for name in observers:   # one viewer, one Foxglove server for the whole fleet
                supervisor.start(name, observer_args(config, name, router, names[0]))
            for name in observers:
                (announce or log.info)(f"{name}: {supervisor.address(name)}")
            pending, released = list(plan), set()

            def finished(robot: str) -> bool:   # its frames done: parked, or its run over
                name = f"robot-{robot}"
                return supervisor.children[name].announced == PARKED or supervisor.exited(name) is not None

            while pending or any(supervisor.exited(f"robot-{r}") is None for r in names if f"robot-{r}" in supervisor.children):
                for robot, start, delay in list(pending):
                    if delay == 0 or recorder.frames_done(names[0]) >= delay or finished(names[0]):
                        (folder / robot).mkdir(parents=True, exist_ok=True)
                        member = robot_config(config, robot, start, origin, router)
                        (folder / robot / "member.json").write_text(member.model_dump_json())
                        supervisor.start(f"robot-{robot}", [str(folder / robot / "member.json"), str(folder / robot),
                                                            "--park"], module="services.pipeline.fleet_member")
                        (announce or log.info)(f"robot {robot}: frames from {start}" +
                                               (f", after robot {names[0]}'s first {delay}" if delay else ""))
                        pending.remove((robot, start, delay))
                for robot in names:
                    name = f"robot-{robot}"
                    code = supervisor.exited(name) if name in supervisor.children else None
                    if code not in (None, 0):
                        raise RunError(f"robot {robot}'s run failed (code {code}): {supervisor.log_tail(name, 2)} "
                                       f"(log: {supervisor.children[name].log_path})")
                if not pending and all(finished(r) for r in names):   # the parked robots end their runs
                    for robot in sorted(set(names) - released):
                        supervisor.children[f"robot-{robot}"].process.send_signal(signal.SIGTERM)
                        released.add(robot)
                if supervisor.exited("fleetmap") is not None:
                    supervisor.restart("fleetmap")
                if progress is not None:
                    progress(sum(recorder.frames_done(r) for r in names), None)
                time.sleep(0.2)
            _drain(supervisor, recorder)
            online = {robot: dict(poses) for robot, poses in recorder.poses.items()}
        if serve:
            kept = [name for name in observers if supervisor.exited(name) is None]
    finally:
        supervisor.stop(["fleetmap"])
        supervisor.stop([n for n in supervisor.children if n not in ("router", *kept)])
        if not kept:
            supervisor.stop(["router"])
    serving = Serving(supervisor, kept) if kept else None
    wall = time.monotonic() - started
    try:
        result = evaluate_fleet(folder, names, online, {r: d for r, _, d in plan})
        result["wall_time_s"] = wall
        result["fleetmap_restarts"] = supervisor.children["fleetmap"].restarts
        write_json(folder / METRICS, {"fleet": result, "robots": {r: _summary(folder / r) for r in names}})
    except BaseException:
        if serving is not None:   # the results could not be written: nothing is left to serve
            serving.close()
        raise
    return folder, result, serving


def _drain(supervisor: Supervisor, recorder: FleetRecorder) -> None:
    """Give the fleet map a moment to take the robots' last messages (its status stops changing)."""
    deadline, last = time.monotonic() + DRAIN_S, None
    while time.monotonic() < deadline:
        statuses = {s.service: s.received for s in health.statuses(recorder.session, topics.FLEET, timeout=0.5)}
        if statuses and statuses == last:
            return
        last = statuses
        time.sleep(0.3)


def _summary(folder: Path) -> dict:
    try:
        metrics = json.loads((folder / METRICS).read_text())
    except (OSError, ValueError):
        return {}
    stages = metrics.get("stages", {})
    loop = metrics.get("services", {}).get("loopclosure", {}).get("extra", {})
    places = loop.get("fleet_places_sent", 0) + loop.get("fleet_places_resent", 0)   # live, and asked for
    sent, camera = loop.get("fleet_bytes_sent", 0), loop.get("camera_bytes", 0)
    return {"frames": metrics.get("summary", {}).get("frames_sent"),
            "map_ate_se2_m": stages.get("map", {}).get("ate_se2", {}).get("rmse"),
            "map_closures": metrics.get("summary", {}).get("map_closures"),
            "fleet_places_sent": places, "fleet_bytes_sent": sent, "camera_bytes": camera,
            "bytes_per_place": sent / places if places else None,
            "fleet_bytes_received": loop.get("fleet_bytes_received", 0),
            "sent_fraction_of_camera": sent / camera if camera else None}


def _truth(folder: Path) -> tuple[dict[int, tuple[float, float, float]], dict[int, float], list]:
    """A robot's frames: true pose (in the first robot's frame) and stamp by map frame, and where its
    own final map puts each frame (frame, experience, offset)."""
    map_log = read_log(folder / MAP_LOG)
    experience_map = map_log.rebuild()
    stamp_of = {step.frame: step.stamp for step in map_log.steps}
    truth = read_tum(folder / "groundtruth.tum")
    planar = truth.planar()
    at_stamp = {round(s, 6): (float(planar[0][i]), float(planar[1][i]), float(planar[2][i]))
                for i, s in enumerate(truth.stamps)}
    poses = {frame: at_stamp[round(stamp, 6)] for frame, stamp in stamp_of.items() if round(stamp, 6) in at_stamp}
    return poses, stamp_of, experience_map.frames


def meeting(truths: dict[str, dict[int, tuple]], starts: dict[str, int], delays: dict[str, int]) -> dict[str, int | None]:
    """Per robot, its first frame at which it, or another robot, comes to a place (within
    MEET_RADIUS_M, facing within MEET_HEADING_RAD) that the other saw earlier: frames of the robots
    are put on one clock by their delays (robot k's i-th frame at tick delay_k + i)."""
    ticks = {}
    for robot, poses in truths.items():
        frames = sorted(poses)
        ticks[robot] = (np.array(frames), np.array([delays[robot] + (f - starts[robot]) for f in frames]),
                        np.array([poses[f] for f in frames]))
    first_tick: dict[str, float] = {r: math.inf for r in truths}
    for one in truths:
        for other in truths:
            if one == other:
                continue
            f1, t1, p1 = ticks[one]
            f2, t2, p2 = ticks[other]
            for start in range(0, len(f1), 256):
                block = p1[start:start + 256]
                near = np.hypot(block[:, None, 0] - p2[None, :, 0], block[:, None, 1] - p2[None, :, 1]) <= MEET_RADIUS_M
                facing = np.abs((block[:, None, 2] - p2[None, :, 2] + np.pi) % (2 * np.pi) - np.pi) <= MEET_HEADING_RAD
                earlier = t2[None, :] < t1[start:start + 256, None]
                hits = np.flatnonzero((near & facing & earlier).any(axis=1))
                if len(hits):
                    tick = float(t1[start + hits[0]])
                    for robot in (one, other):
                        first_tick[robot] = min(first_tick[robot], tick)
                    break
    result = {}
    for robot, tick in first_tick.items():
        if math.isinf(tick):
            result[robot] = None
        else:
            result[robot] = int(starts[robot] + max(0.0, tick - delays[robot]))
    return result


def evaluate_fleet(folder: Path, names: list[str], online: dict, delays: dict[str, int]) -> dict:
    """The fleet's results (module docstring): writes fleet/<robot>.tum and .groundtruth.tum."""
    fleet = read_fleet_log(folder / FLEET / FLEET_LOG)
    final = fleet.final_poses()
    truths, stamps, placed, ate, online_error = {}, {}, {}, {}, {}
    starts = {}
    for robot in names:
        truths[robot], stamps[robot], frames = _truth(folder / robot)
        starts[robot] = min(truths[robot]) if truths[robot] else 0
        poses = final.get(robot)
        frames = [(f, e, o) for f, e, o in frames if poses is not None and e < len(poses) and f in truths[robot]]
        placed[robot] = {f: compose(tuple(poses[e]), o) for f, e, o in frames}
        ordered = sorted(placed[robot])
        if ordered:
            write_tum(folder / FLEET / f"{robot}.tum", Trajectory.from_planar(
                [stamps[robot][f] for f in ordered], *(np.array([placed[robot][f][i] for f in ordered]) for i in range(3))))
        truth_frames = sorted(truths[robot])
        write_tum(folder / FLEET / f"{robot}.groundtruth.tum", Trajectory.from_planar(
            [stamps[robot][f] for f in truth_frames], *(np.array([truths[robot][f][i] for f in truth_frames]) for i in range(3))))
        if fleet.joined(robot) and ordered:
            errors = np.array([math.dist(placed[robot][f][:2], truths[robot][f][:2]) for f in ordered])
            ate[robot] = float(np.sqrt(np.mean(errors ** 2)))
        else:
            ate[robot] = None
        joined_at = fleet.joined_at.get(robot)
        at_stamp = {round(stamps[robot][f], 6): f for f in truths[robot]}
        after = [(truths[robot][at_stamp[round(p[3], 6)]], p) for seq, p in sorted(online.get(robot, {}).items())
                 if p[4] and round(p[3], 6) in at_stamp and (joined_at is None or at_stamp[round(p[3], 6)] >= joined_at)]
        if after:
            write_tum(folder / FLEET / f"{robot}.online.tum", Trajectory.from_planar(
                [p[3] for _, p in after], *(np.array([p[i] for _, p in after]) for i in range(3))))
            errors = np.array([math.dist(t[:2], p[:2]) for t, p in after])
            online_error[robot] = {"frames": len(errors), "max": float(errors.max()),
                                   "rmse": float(np.sqrt(np.mean(errors ** 2)))}
    decided = {"confirmed": 0, "accepted": 0, "accepted_false": 0, "rejected": 0, "rejected_false": 0, "pending": 0,
               "unmeasured": 0}
    largest = None
    for closure in fleet.closures:
        decided["confirmed"] += 1
        decided[closure.fate] += 1
        one, other = truths[closure.robot].get(closure.frame), truths[closure.matched_robot].get(closure.matched_frame)
        if one is None or other is None:
            continue
        distance = math.dist(one[:2], other[:2])
        if closure.fate in ("accepted", "rejected") and not same_place(one[:2], other[:2]):
            decided[f"{closure.fate}_false"] += 1
        if closure.fate == "accepted":
            largest = distance if largest is None else max(largest, distance)
    meet = meeting(truths, starts, delays)
    joined_at = {robot: fleet.joined_at.get(robot) for robot in names}
    placed_at = {robot: fleet.placed_at.get(robot) for robot in names}
    both = [(placed[r][f], truths[r][f]) for r in names if fleet.joined(r) for f in sorted(placed[r])]
    whole = None
    if len(both) >= 3:
        estimate = np.array([p for p, _ in both])
        reference = np.array([t for _, t in both])
        stamps_all = np.arange(len(both), dtype=float)
        whole = {"frames": len(both),
                 "ate_se2_rmse_m": trajectory_metrics.ate(
                     Trajectory.from_planar(stamps_all, *estimate.T), Trajectory.from_planar(stamps_all, *reference.T),
                     align="se2")["rmse"],
                 "error_unaligned_rmse_m": float(np.sqrt(np.mean(np.sum((estimate[:, :2] - reference[:, :2]) ** 2, axis=1))))}
    return {"robots": names, "frame_robot": fleet.frame_robot,
            "inter_robot_closures_confirmed": decided["confirmed"],
            "inter_robot_closures_accepted": decided["accepted"],
            "inter_robot_closures_accepted_false": decided["accepted_false"],
            "inter_robot_closures_rejected": decided["rejected"],
            "inter_robot_closures_rejected_false": decided["rejected_false"],
            "inter_robot_closures_pending": decided["pending"],
            "inter_robot_closures_unmeasured": decided["unmeasured"],
            "accepted_largest_distance_m": largest,
            "joined_at": joined_at, "placed_at": placed_at, "ate_m": ate, "online_error_after_join_m": online_error,
            "first_meeting": meet,
            "frames_to_join": {r: (placed_at[r] - meet[r]) if placed_at[r] is not None and meet[r] is not None
                               and r != fleet.frame_robot else None for r in names},
            "whole_fleet": whole}


def summary_rows(result: dict, robots: dict) -> list[tuple[str, object, str]]:
    rows = [("robots", ", ".join(result["robots"]), f"fleet frame: robot {result['frame_robot']}'s map"),
            ("wall time", result.get("wall_time_s"), "s"),
            ("inter-robot closures confirmed", result["inter_robot_closures_confirmed"], ""),
            ("inter-robot closures accepted / rejected / pending", f"{result['inter_robot_closures_accepted']} / "
             f"{result['inter_robot_closures_rejected']} / {result['inter_robot_closures_pending']}", ""),
            ("inter-robot closures accepted: false", result["inter_robot_closures_accepted_false"],
             f"false: frames > {TRUE_CLOSURE_M:g} m apart")]
    for robot in result["robots"]:
        summary = robots.get(robot, {})
        rows.append((f"{robot}: joined at frame", result["joined_at"][robot], f"its newest frame then: "
                     f"{result.get('placed_at', {}).get(robot)}"))
        rows.append((f"{robot}: first meeting, frames to join", f"{result['first_meeting'][robot]}, "
                     f"{result['frames_to_join'][robot]}", "frames"))
        rows.append((f"{robot}: fleet-frame error, no alignment (final map)", result["ate_m"][robot], "m (RMSE)"))
        if robot in result["online_error_after_join_m"]:
            error = result["online_error_after_join_m"][robot]
            rows.append((f"{robot}: published fleet poses after joining: max / RMSE",
                         f"{error['max']:.4g} / {error['rmse']:.4g}", "m"))
        rows.append((f"{robot}: own map ATE (SE(2))", summary.get("map_ate_se2_m"), "m"))
        if summary.get("bytes_per_place"):
            rows.append((f"{robot}: places sent, bytes per place", f"{summary['fleet_places_sent']}, "
                         f"{summary['bytes_per_place']:.0f}", "B"))
            rows.append((f"{robot}: sent to other robots / camera data read",
                         f"{100 * summary['sent_fraction_of_camera']:.2f}", "%"))
    if result.get("whole_fleet"):
        whole = result["whole_fleet"]
        rows.append(("fleet map, every robot's frames: ATE (SE(2)) / no alignment",
                     f"{whole['ate_se2_rmse_m']:.4g} / {whole['error_unaligned_rmse_m']:.4g}", "m"))
    return rows


def run_fleet_command(args, config: RunConfig, progress=None) -> int:
    """`gridslam run --fleet` / `demo --fleet`: run, print the table."""
    from services.evaluation.results import format_table
    from services.source.spec import open_source
    from services.pipeline.runner import source_settings

    settings = source_settings(config)
    frames = open_source(config.source, start=config.start, stop=None, step=config.step, preset=settings.preset,
                         calibration=settings.calibration, world=settings.world(), fov=settings.fov)
    total = None if getattr(frames, "live", False) else len(frames) + config.start
    plan = fleet_plan(args, config, total)
    if total is not None:
        for robot, start, _ in plan:
            if start >= total:
                raise ConfigError(f"--robot-start {start} (robot {robot}): the source has {total} frames")
    folder, result, serving = run_fleet(config, plan, args.out, progress=progress, overwrite=args.overwrite,
                                        announce=lambda line: print(line, flush=True), serve=True)
    try:
        robots = json.loads((folder / METRICS).read_text())["robots"]
        print(format_table(summary_rows(result, robots)))
        print(f"results: {folder}")
        if serving is not None:   # --view, --foxglove: time to look at the finished fleet
            addresses = ", ".join(f"{name} {address}" for name, address in serving.addresses.items())
            print(f"the fleet has finished; serving it until Ctrl-C: {addresses}", flush=True)
            serving.wait()
    finally:
        if serving is not None:
            serving.close()
    return 0
