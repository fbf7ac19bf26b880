"""expmap: the experience map of grid-cell odometry, view templates and loop closures: a pose
graph (gtsam iSAM2) with metric closures by default, RatSLAM's relaxation and snap-to-experience
as the paper's model (graph.py). Writes loop_closures.csv: every confirmed closure, its
measurement and whether the map accepted it.

The map is kept as a journal of its inputs with a checkpoint beside it (store.py): when the
store's CheckpointPolicy (`checkpoint_updates`, `checkpoint_frames`) says so, the map is rebased
and its state written in a background thread; a restart restores it and replays only the
frames after it."""

from __future__ import annotations

import argparse
import bisect
import collections
import csv
import logging
import math
import shutil
import threading
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, create_model

from schemas import (Experience, FramePlacement, GridPose, Link, LoopClosure, MapFrames, MapPose, MapRoute, MapSnapshot,
                     MapUpdate, Point, ViewTemplate)
from services.common.config import load_config
from services.common.convert import planar_pose
from services.common.errors import ConfigError, DataError, PersistenceError
from services.common.journal import SESSION, continue_session
from services.common.layout import MapReuseParams, add_map_reuse_arguments, map_files, session_base
from services.common.runtime import RuntimeConfig
from services.common.recovery import REPLAY_FRAMES
from services.common.service import Service
from services.common.settings import add_flag, config_fields, params_of
from services.expmap.graph import ExperienceMap, FrameResult, MapParams, MapState
from services.expmap.joiner import FrameJoiner
from services.expmap.links import MOVED, ClosureInput
from services.expmap.route import shortest_route
from services.expmap.store import (
    CheckpointPolicy,
    MapStore,
    Step,
    checkpoint_path,
    header,
)

log = logging.getLogger(__name__)

# Odometry beyond these is no robot's (10,000 km; a million radians of accumulated turning): such
# a pose would overflow the map's arithmetic after it was journaled, so it is rejected before.
MAX_COORDINATE_M = 1e7
MAX_HEADING_RAD = 1e6
MAX_FRAMES_REPLY = 5000   # frames in one map/frames reply (the fleet map asks again from the next)


class MapInputError(DataError):
    """A grid pose the map cannot take (the message says which value)."""


class _ExpMapFields(BaseModel):
    """Configuration of the expmap service (table `[expmap]`, env `GRIDSLAM_EXPMAP_*`, presets).
    The map's keys are MapParams' (services/expmap/graph.py declares each)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    store: Path = Field(Path("experience_map.log"), description="Append-only map log; a restart resumes from it.")
    checkpoint_updates: int = Field(
        500, ge=0, description="Solver updates between checkpoints of the map beside its log (a restart replays only the "
                               "frames after the last); 0: none.")
    checkpoint_frames: int = Field(50, ge=1, description="Fewest frames between checkpoints.")
    out: Path | None = Field(None, description="Folder for loop_closures.csv (none: not written).")

    def params(self) -> MapParams:
        return params_of(MapParams, self)


ExpMapConfig = create_model("ExpMapConfig", __base__=_ExpMapFields, __doc__=_ExpMapFields.__doc__,
                            **config_fields(MapReuseParams), **config_fields(MapParams))


CLOSURE_COLUMNS = ("frame", "matched_frame", "matched_template", "votes", "measurement", "forward", "left", "yaw",
                   "inliers", "geometry_error", "innovation", "accepted")


def experience_message(experience_map: ExperienceMap, index: int) -> Experience:
    x, y, heading = experience_map.poses[index]
    return Experience(id=index, x=float(x), y=float(y), heading=float(heading),
                      template_id=experience_map.templates[index], frame=experience_map.created[index])


def link_message(link, covariance=None) -> Link:
    """The wire form of a link, with its covariance in the pose graph when there is one (the fleet map's input)."""
    return Link(**asdict(link), covariance=None if covariance is None else
                [float(v) for v in (np.asarray(covariance) + np.asarray(covariance).T).ravel() / 2])


def link_covariances(experience_map: ExperienceMap, start: int, stop: int) -> list:
    """The covariances of the map's links start..stop-1 (None each under an optimiser without them)."""
    covariances = getattr(experience_map.optimizer, "covariances", None)
    return list(covariances[start:stop]) if covariances is not None and len(covariances) >= stop else [None] * (stop - start)


def frame_placements(experience_map: ExperienceMap, first: int, last: int) -> list[FramePlacement]:
    """Where the map puts its frames `first`..`last`: the experience and the offset from it."""
    start = bisect.bisect_left(experience_map.frames, first, key=lambda row: row[0])
    placements = []
    for frame, experience, (dx, dy, dheading) in experience_map.frames[start:start + MAX_FRAMES_REPLY]:
        if frame > last:
            break
        placements.append(FramePlacement(frame=frame, experience=experience, dx=dx, dy=dy, dheading=dheading))
    return placements


def closure_row(frame: int, c: ClosureInput, fate: str, residual: float | None) -> tuple:
    """loop_closures.csv's row of a closure the map decided on (``frame``: the revisiting frame)."""
    return (frame, c.matched_frame, c.matched_template, c.votes, c.method or "none", f"{c.forward:.4f}",
            f"{c.left:.4f}", f"{c.yaw:.5f}", c.inliers, c.geometry_error, "" if residual is None else f"{residual:.3f}",
            str(fate == "accepted").lower())


def closure_input(message: LoopClosure, frame: int) -> ClosureInput:
    """The map's view of a confirmed closure of the map's frame ``frame``: the matched place and
    the measurement, if any; ``frame`` set when the closure is of an earlier frame."""
    evidence = {"votes": message.votes, "inliers": message.inliers, "geometry_error": message.geometry_error,
                "frame": message.frame if message.frame != frame else -1}
    pose = message.relative_pose
    if message.measurement == "none" or pose is None or message.covariance is None:
        return ClosureInput(message.matched_template, message.matched_frame, **evidence)
    return ClosureInput(message.matched_template, message.matched_frame, message.measurement, pose.forward, pose.left,
                        pose.yaw, tuple(message.covariance), **evidence)


class ExpMapService(Service):
    name = "expmap"
    exclusive = True   # the map grows with every frame

    def __init__(self, runtime: RuntimeConfig, config: ExpMapConfig, instance: str | None = None):
        super().__init__(runtime, instance)
        self.config = config
        if config.map is not None and not (config.store.exists() and config.store.stat().st_size):
            start_session(config)
        self.store = MapStore(config.store, config.params(),
                              CheckpointPolicy(min_steps=config.checkpoint_frames, updates=config.checkpoint_updates))
        last_session = self.store.sessions[-1][1] if self.store.sessions else None
        self.base = session_base(last_session[SESSION]) if last_session else 0   # this session's first frame number
        self.lock = threading.Lock()   # map/snapshot reads on a Zenoh thread while frames are applied
        # Results of the last frames, to answer a re-sent frame that is already in the map.
        self.recent: collections.OrderedDict[int, FrameResult] = collections.OrderedDict()
        self.csv_path = config.out / "loop_closures.csv" if config.out else None
        self.writer: threading.Thread | None = None   # writes the last checkpoint
        started = time.perf_counter()
        self.map, restored, extras = self.store.rebuild(each=lambda step, result: self._remember(result))
        for frame, experience, x, y, heading in extras.get("recent", []):   # before the checkpoint: not replayed
            self.recent[int(frame)] = FrameResult(int(frame), int(experience), (float(x), float(y), float(heading)))
        self.recent = collections.OrderedDict(sorted(self.recent.items())[-REPLAY_FRAMES:])
        closure_of = {(c.frame if c.frame >= 0 else step.frame, c.matched_frame): c
                      for step in self.store.steps for c in step.closures}
        rows = [closure_row(frame, closure_of[(frame, matched)], fate, residual)
                for (frame, matched, fate), residual in zip(self.map.decisions, self.map.residuals)]
        if self.csv_path is not None:   # written afresh from the journal: a crash never leaves it behind
            try:
                self.csv_path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as error:
                raise PersistenceError(f"{self.csv_path.parent}: cannot create ({error.strerror or error})") from None
            self._write_closures(rows, "w")
        if self.store.steps:
            log.info("expmap resumed from %s in %.2f s: %d frames (%s), %d experiences, %d links", config.store,
                     time.perf_counter() - started, len(self.store.steps),
                     f"checkpoint after {restored}, {len(self.store.steps) - restored} replayed" if restored else "all replayed",
                     len(self.map), len(self.map.links))
        self.joiner = FrameJoiner()   # the frames' three inputs, joined by seq (joiner.py)
        self._last_header = None   # of the last map/update or map/pose published

    def setup(self) -> None:
        self.subscribe("grid/pose", self.on_grid_pose)
        self.subscribe("view/template", self.on_view)
        # Several closures share a frame's seq (a confirmed run's): the repeated seq is not stale here.
        self.subscribe("loop/closure", self.on_closure, sparse=True, drop_stale=False)
        self.queryable("map/snapshot", self.snapshot)
        self.queryable("map/route", self.route, parameters=True)
        self.queryable("map/frames", self.frames, parameters=True)

    def teardown(self) -> None:
        if self.writer is not None:
            self.writer.join()
        self.store.close()
        self._publish_final()

    def _publish_final(self) -> None:
        """On a clean stop: the experiences whose best estimate differs from what was published
        (frame by frame the map refreshes a bounded number of them), so observers end with the map
        the run's results hold."""
        if self._last_header is None or not len(self.map):
            return
        final = self.map.final_poses()
        changed = np.flatnonzero((np.abs(final - self.map.poses) > MOVED).any(axis=1))
        if len(changed):
            self._send("map/update", MapUpdate(
                header=self._last_header, experiences=[
                    Experience(id=int(i), x=float(final[i, 0]), y=float(final[i, 1]), heading=float(final[i, 2]),
                               template_id=self.map.templates[i], frame=self.map.created[i]) for i in changed],
                links=[], experience_count=len(self.map), link_count=len(self.map.links)))

    def on_grid_pose(self, message: GridPose) -> None:
        position = message.pose.position
        if max(abs(position.x), abs(position.y)) > MAX_COORDINATE_M or abs(message.heading) > MAX_HEADING_RAD:
            raise MapInputError(f"grid pose ({position.x:.3g}, {position.y:.3g}) m, heading {message.heading:.3g} rad "
                                f"is beyond {MAX_COORDINATE_M:g} m or {MAX_HEADING_RAD:g} rad")
        self.joiner.pose(message.header.seq, message)
        self._advance()

    def on_view(self, message: ViewTemplate) -> None:
        self.joiner.view(message.header.seq, message, max(message.loop_closures, int(message.loop_closure)))
        self._advance()

    def on_closure(self, message: LoopClosure) -> None:
        if not self.joiner.closure(message.header.seq, message.frame, message, self._mapped()):
            self.counters.stale += 1   # a frame re-sent after a restart: the map has it, or has it in hand
            return
        self._advance()

    def _mapped(self) -> int | None:
        """The last seq of this session the map holds (None: none)."""
        return None if self.map.last_frame is None else self.map.last_frame - self.base

    def _advance(self) -> None:
        """Apply every frame whose inputs are all in, in frame order (the map is deterministic in
        its input order, whatever order the topics' messages arrive in)."""
        while (joined := self.joiner.next(self._mapped())) is not None:
            pose, view, frame = joined.pose, joined.view, self.base + joined.seq
            if joined.in_map:
                if frame in self.recent:   # already in the map (a re-sent frame after a restart): answer again
                    self._publish_pose(pose, self.recent[frame])
                continue
            own = next((closure_input(c, frame) for c in joined.closures if c.frame == frame), None)
            earlier = tuple(closure_input(c, frame) for c in joined.closures if c.frame != frame)
            step = Step(frame, pose.header.stamp.to_seconds(), (pose.pose.position.x, pose.pose.position.y, pose.heading),
                        view.template_id, own, tuple(pose.increment_covariance) if pose.increment_covariance is not None
                        else None, earlier)
            self.store.append(step)   # on disk before anything is published
            with self.lock:
                result = step.apply(self.map)
            self._remember(result)
            if self.csv_path is not None and result.decisions:
                self._write_closures([closure_row(c.frame if c.frame >= 0 else frame, c, fate, residual)
                                      for c, fate, residual in result.decisions], "a")
            for part in result.joined:
                log.info("expmap: frame %d joins part %d of the map to its frame", frame, part)
            if result.placed or result.lost:
                log.warning("expmap: frame %d: %s", frame, "localised on the map" if result.placed else
                            f"lost: no closure accepted for {self.map.localizer.params.lost_distance:g} m; searching")
            self._publish(pose, result)
            if self.store.checkpoint_due(self.map):
                self._checkpoint()

    def _checkpoint(self) -> None:
        """Rebase the map at a checkpoint recorded in the journal, and write its state beside it
        in a background thread (the previous write joined first)."""
        if self.writer is not None:
            self.writer.join()
        with self.lock:
            meta, state = self.store.checkpoint(self.map)
        recent = np.array([(r.frame, r.experience, *r.pose) for r in self.recent.values()], dtype=float).reshape(-1, 5)
        self.writer = threading.Thread(target=self._write_checkpoint, args=(meta, state, {"recent": recent}),
                                       name="expmap-checkpoint", daemon=True)
        self.writer.start()

    def _write_checkpoint(self, meta: dict, state: dict, extras: dict) -> None:
        try:
            self.store.write_checkpoint(meta, state, extras)
        except OSError as error:   # the journal still holds the map: a restart replays more of it
            log.warning("%s: cannot write the map checkpoint (%s)", self.store.path, error.strerror or error)

    def _publish(self, pose: GridPose, result: FrameResult) -> None:
        self._last_header = pose.header.model_copy(update={"frame_id": "map"})
        if result.new_experiences or result.new_links or result.moved:
            changed = sorted(set(result.new_experiences) | set(result.moved))
            self.publish("map/update", MapUpdate(
                header=pose.header.model_copy(update={"frame_id": "map"}),
                experiences=[experience_message(self.map, i) for i in changed],
                links=[link_message(link, covariance) for link, covariance in
                       zip(result.new_links, link_covariances(self.map, len(self.map.links) - len(result.new_links),
                                                              len(self.map.links)))],
                experience_count=len(self.map), link_count=len(self.map.links)))
        self._publish_pose(pose, result)

    def _publish_pose(self, pose: GridPose, result: FrameResult) -> None:
        x, y, heading = result.pose
        placement = None if result.offset is None else FramePlacement(
            frame=result.frame, experience=result.experience, dx=result.offset[0], dy=result.offset[1],
            dheading=result.offset[2])
        self.publish("map/pose", MapPose(header=pose.header.model_copy(update={"frame_id": "map"}),
                                         pose=planar_pose(x, y, heading), heading=heading,
                                         experience_id=max(result.experience, 0), localized=result.localized,
                                         placement=placement))

    def _remember(self, result: FrameResult) -> None:
        self.recent[result.frame] = result
        while len(self.recent) > REPLAY_FRAMES:
            self.recent.popitem(last=False)

    def snapshot(self) -> MapSnapshot:
        """Called on a Zenoh thread: the map as of one frame, copied under the lock, serialised outside it."""
        with self.lock:
            state: MapState = self.map.snapshot()
            covariances = link_covariances(self.map, 0, len(state.links))
        return MapSnapshot(header=self.header(state.frame or 0, 0.0, "map"),
                           experiences=[Experience(id=i, x=float(x), y=float(y), heading=float(heading),
                                                   template_id=state.templates[i], frame=state.created[i])
                                        for i, (x, y, heading) in enumerate(state.poses)],
                           links=[link_message(link, covariance) for link, covariance in zip(state.links, covariances)])

    def frames(self, parameter) -> MapFrames:
        """Called on a Zenoh thread: where the map puts the frames `from`..`to` (map/frames?from=F;to=T)."""
        first, last = (parse_frame(parameter(name), name) for name in ("from", "to"))
        with self.lock:
            frame = self.map.last_frame or 0
            placements = frame_placements(self.map, first, last)
        return MapFrames(header=self.header(frame, 0.0, "map"), frames=placements)

    def route(self, parameter) -> MapRoute:
        """Called on a Zenoh thread: the shortest route between the points the query's parameters
        `from=X,Y` and `to=X,Y` name (map frame, m); also published on map/route for the viewer."""
        start, goal = (parse_point(parameter(name), name) for name in ("from", "to"))
        with self.lock:
            state: MapState = self.map.snapshot()
        route = shortest_route(state.poses, state.links, start, goal)
        message = route_message(route, start, goal, self.header(state.frame or 0, 0.0, "map"))
        self._send("map/route", message)
        return message

    def _write_closures(self, rows: list[tuple], mode: str) -> None:
        try:
            with open(self.csv_path, mode, newline="") as handle:
                writer = csv.writer(handle)
                if mode == "w":
                    writer.writerow(CLOSURE_COLUMNS)
                writer.writerows(rows)
        except OSError as error:
            raise PersistenceError(f"{self.csv_path}: cannot write ({error.strerror or error})") from None

    def extra_counters(self) -> dict[str, float]:
        closures = self.map.closures
        return {**super().extra_counters(), "experiences": len(self.map), "links": len(self.map.links),
                "frames_in_map": len(self.map.frames), "frames_skipped": self.joiner.skipped,
                "closures_accepted": closures["accepted"], "closures_rejected": closures["rejected"],
                "closures_unmeasured": closures["unmeasured"]}


def start_session(config: ExpMapConfig) -> None:
    """Begin the session's journal as the saved map's (checked, read only) and copy its checkpoint."""
    saved = map_files(config.map)["map"]
    continue_session(saved, config.store, header(config.params()), config.localize, config.map)
    if checkpoint_path(saved).exists():
        try:
            shutil.copyfile(checkpoint_path(saved), checkpoint_path(config.store))
        except OSError as error:   # the journal holds the map: a restart replays all of it
            log.warning("%s: cannot copy the map's checkpoint (%s)", checkpoint_path(saved), error.strerror or error)


def parse_point(text: str | None, name: str) -> tuple[float, float]:
    """A point X,Y of a route query's parameter ``name``."""
    try:
        x, y = (float(v) for v in (text or "").split(","))
    except ValueError:
        raise ConfigError(f"map/route: parameter {name!r} must be X,Y in metres, got {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ConfigError(f"map/route: parameter {name!r} must be finite, got {text!r}")
    return x, y


def parse_frame(text: str | None, name: str) -> int:
    """A frame number of a map/frames query's parameter ``name``."""
    try:
        value = int(text or "")
    except ValueError:
        raise ConfigError(f"map/frames: parameter {name!r} must be a frame number, got {text!r}") from None
    if value < 0:
        raise ConfigError(f"map/frames: parameter {name!r} must be ≥ 0, got {text!r}")
    return value


def route_message(route, start, goal, header) -> MapRoute:
    return MapRoute(header=header, start=Point(x=start[0], y=start[1]), goal=Point(x=goal[0], y=goal[1]),
                    experiences=route.experiences, poses=[planar_pose(*pose) for pose in route.poses],
                    length=route.length, found=route.found)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", help="map parameters for a dataset: synthetic, nubot, kitti, stlucia")
    parser.add_argument("--store", type=Path, help="map log file (default experience_map.log); a restart resumes from it")
    parser.add_argument("--out", type=Path, help="folder for loop_closures.csv")
    add_map_arguments(parser)
    add_map_reuse_arguments(parser)


def add_map_arguments(parser: argparse.ArgumentParser) -> None:
    """The map's model, shared by every command that builds a map (run, demo, map build, the service)."""
    add_flag(parser, MapParams, "closure")
    add_flag(parser, MapParams, "optimizer", flag="--map-optimizer", dest="map_optimizer")


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    config = load_config(ExpMapConfig, "expmap", preset=args.preset, config_file=args.config,
                         overrides={"store": args.store, "out": args.out, "closure": args.closure,
                                    "optimizer": args.map_optimizer, "map": args.map, "localize": args.localize})
    if config.localize and config.map is None:
        raise ConfigError("[expmap] localize: localisation needs a saved map (--map DIR)")
    return ExpMapService(runtime, config, args.instance).run()
