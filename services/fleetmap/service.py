"""fleetmap: one robust pose graph over every robot's experience map (graph.py), joined by the
inter-robot closures the robots' loop closures confirm; each robot's pose in the fleet frame.

It serves the whole fleet under the key chunk `fleet` (docs/fleet.md): it subscribes to every
robot's `map/update` (experiences, links with their covariances), `map/pose` and `fleet/closure`,
and publishes `fleet/<robot>/pose` (FleetPose), `fleet/update` (FleetUpdate, at most every
UPDATE_PERIOD_S) and answers `fleet/snapshot`. Its inputs are journaled in the order applied
(store.py), so a restart rebuilds the same map; it then catches up: a robot's map it lacks, or
lacks a part of (a `map/update` whose links do not follow on from the ones it has, or the robot's
expmap status counting more than it holds), comes from that robot's `map/snapshot`; closures it
missed, from the robot's `fleet/closures?from=N` (asked every `sync_period` seconds of every live
loopclosure). A closure's frames are placed by the robot's `map/frames` (its map's own record of
each frame) once its `map/pose` has passed them. A robot's own map does not wait for any of this:
the fleet map only listens."""

from __future__ import annotations

import argparse
import bisect
import logging
import threading
import time
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, create_model

from schemas import (FleetClosures, FleetExperience, FleetLink, FleetPose, FleetRobot, FleetSnapshot, FleetUpdate, MapFrames,
                     MapPose, MapSnapshot, MapUpdate)
from services.common import codec, health, topics
from services.common.config import load_config
from services.common.convert import heading_of, planar_pose
from services.common.errors import ConfigError
from services.common.geometry import between
from services.common.recovery import sent_again
from services.common.runtime import RuntimeConfig
from services.common.service import Service
from services.common.settings import config_fields, params_of
from services.fleetmap.catchup import ClosureIntake, FramePlacements, map_increment
from services.fleetmap.consistency import ConsistencyParams
from services.fleetmap.graph import ClosureInput, FleetParams, Result
from services.fleetmap.store import FleetStore, closure_record, map_record

log = logging.getLogger(__name__)

UPDATE_PERIOD_S = 0.5
QUERY_TIMEOUT_S = 3.0
FRAMES_KEPT = 200_000   # frame placements kept per robot (from map/pose and map/frames), for closures of earlier frames
FRAMES_PATIENCE = 10    # sync periods without an answer from a robot's map/frames before its map/pose places frames


class _Fields(BaseModel):
    """Configuration of the fleetmap service (table `[fleetmap]`, env `GRIDSLAM_FLEETMAP_*`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    store: Path = Field(Path("fleet_map.log"), description="Append-only journal of the fleet map's inputs; a restart "
                                                           "resumes from it.")
    sync_period: float = Field(3.0, gt=0, description="Seconds between asking the live robots for what the fleet map lacks.")
    checkpoint_events: int = Field(2000, ge=0, description="Inputs between checkpoints of the fleet map (0: none).")


FleetMapConfig = create_model("FleetMapConfig", __base__=_Fields, __doc__=_Fields.__doc__,
                              **config_fields(FleetParams), **config_fields(ConsistencyParams, "consistency_"))


class _Robot:
    """What the adapter knows of one robot beyond the fleet map's inputs (not journaled)."""

    def __init__(self, sync_period: float):
        self.poses: dict[int, tuple[float, float, float]] = {}   # its experiences in its own map, as last published
        self.frames = FramePlacements(FRAMES_KEPT, sync_period, FRAMES_PATIENCE * sync_period)
        self.needs_snapshot = False
        self.pose_seq: int | None = None   # the newest frame whose fleet pose went out


class FleetMapService(Service):
    name = "fleetmap"
    exclusive = True   # one fleet map per fleet
    # It listens to the robots and must never slow them: a sample that finds the inbox full is
    # dropped (counted), and what it carried comes again from the catch-up (a map/update that does
    # not follow on, a closure index skipped).
    observer = True
    inbox_size = 1024

    def __init__(self, runtime: RuntimeConfig, config, instance: str | None = None):
        super().__init__(runtime, instance)
        self.config = config
        self.params = params_of(FleetParams, config)
        self.consistency = params_of(ConsistencyParams, config, "consistency_")
        self.store = FleetStore(config.store, self.params, self.consistency, config.checkpoint_events)
        self.lock = threading.Lock()   # the snapshot is read on a Zenoh thread
        self.feeds: dict[str, _Robot] = {}
        self.intake = ClosureIntake()   # closures taken once each, waiting until both maps place them
        started = time.perf_counter()
        self.fleet, restored = self.store.rebuild(each=self._remember)
        if self.store.inputs:
            log.info("fleetmap resumed from %s in %.2f s: %d inputs (%s), robots %s", config.store,
                     time.perf_counter() - started, len(self.store.inputs),
                     f"checkpoint after {restored}" if restored else "all replayed", ", ".join(self.fleet.robots))
        self.changed: set[tuple[str, int]] = set()
        self.decided: dict[tuple[str, int], object] = {}
        self.last_update = 0.0
        self.next_sync = 0.0
        self._last_header = None

    def _feed(self, robot: str) -> _Robot:
        return self.feeds.setdefault(robot, _Robot(self.config.sync_period))

    def _remember(self, record: dict, result: Result) -> None:
        """A journaled input replayed: what the adapter derives from it."""
        if "map" in record:
            feed = self._feed(record["map"])
            for ident, x, y, heading, _ in record["experiences"]:
                feed.poses[int(ident)] = (x, y, heading)
        else:
            self.intake.replayed(record["closure"]["robot"], record["closure"]["index"])

    # --- wiring -----------------------------------------------------------------------------------
    def setup(self) -> None:
        self.subscribe("map/update", self.on_map_update, robot="*", sparse=True, drop_stale=False)
        self.subscribe("map/pose", self.on_map_pose, robot="*", sparse=True, drop_stale=False)
        self.subscribe("fleet/closure", self.on_closures, robot="*", sparse=True, drop_stale=False)
        self.queryable("snapshot", self.snapshot)

    def teardown(self) -> None:
        self._publish_update(force=True)
        self.store.close()

    def on_idle(self) -> None:
        self._publish_update()
        self._maybe_sync()

    # --- robots' maps ----------------------------------------------------------------------------
    def on_map_update(self, message: MapUpdate) -> None:
        robot = message.header.robot
        if robot == topics.FLEET:
            return
        feed = self._feed(robot)
        for e in message.experiences:
            feed.poses[e.id] = (e.x, e.y, e.heading)
        increment = map_increment(*self._known(robot), message.experiences, message.link_count - len(message.links),
                                  message.links)
        if increment is None:
            feed.needs_snapshot = True   # a part of its map went by while the fleet map was not listening
            self._sync_robot(robot)
            return
        self._grow(robot, *increment, message.header)

    def _known(self, robot: str) -> tuple[int, int]:
        """The experiences and links the fleet map has of a robot's map."""
        state = self.fleet.robots.get(robot)
        return (len(state.poses), state.links) if state else (0, 0)

    def _grow(self, robot: str, experiences: list, links: list, header) -> None:
        if not experiences and not links:
            return
        experiences = [(e.id, e.x, e.y, e.heading, e.frame) for e in experiences]
        if any(link.covariance is None for link in links):
            raise ConfigError(f"fleetmap: robot {robot}'s map/update has links without a covariance (its expmap must be "
                              "the pose graph, optimizer gtsam)")
        rows = [(link.source, link.target, link.dx, link.dy, link.dheading, link.loop_closure, link.accepted,
                 list(link.covariance)) for link in links]
        record = map_record(robot, experiences, rows)
        self.store.append(record)
        with self.lock:
            result = self.fleet.add_map(robot, [tuple(e) for e in experiences], rows)
        self._after(result, header)
        self._resolve()

    def on_map_pose(self, message: MapPose) -> None:
        robot = message.header.robot
        feed = self._feed(robot)
        experience = message.experience_id
        pose = (message.pose.position.x, message.pose.position.y, heading_of(message.pose))
        state = self.fleet.robots.get(robot)
        placement = message.placement
        if placement is not None or experience in feed.poses:
            # The map's own placement of the frame; a pose against the experience's pose as last
            # heard lags when the map/update that moved it comes after this map/pose (per key order only).
            offset = (placement.dx, placement.dy, placement.dheading) if placement is not None else \
                between(feed.poses[experience], pose)
            feed.frames.pose(message.header.seq, experience, offset, recorded=placement is not None)
            if state is not None and experience < len(state.poses) and not sent_again(feed.pose_seq, message.header.seq):
                feed.pose_seq = message.header.seq   # a map/pose sent again (its expmap's kept outputs) is not published twice
                x, y, heading = self.fleet.pose(robot, experience, offset)
                self._send(topics.fleet_pose_topic(robot), FleetPose(
                    header=message.header.model_copy(update={"frame_id": "map"}), pose=planar_pose(x, y, heading),
                    heading=heading, experience_id=experience, joined=self.fleet.joined(robot)))
                self.counters.published += 1
        if state is None and experience not in feed.poses:
            feed.needs_snapshot = True
        if any(name == robot for name, _ in self.intake.waiting):
            self._resolve()
        self._publish_update()
        self._maybe_sync()

    # --- inter-robot closures --------------------------------------------------------------------
    def on_closures(self, message: FleetClosures) -> None:
        robot = message.header.robot
        if self.intake.missed(robot, message.closures):
            self._fetch_closures(robot)   # some were missed: ask for them, in order
        self.intake.take(robot, message.closures)
        self._resolve()

    def _placed(self, robot: str, record):
        placed = self._placement(robot, record.frame), self._place_of(record.matched_robot, record.matched_frame)
        return None if None in placed else placed

    def _resolve(self) -> None:
        """Place the waiting closures whose frames both maps now have (in the order they came)."""
        for robot, record, placed in self.intake.place(self._placed):
            (experience, offset), (matched_experience, matched_offset) = placed
            measured = record.relative_pose is not None and record.covariance is not None
            closure = ClosureInput(robot, record.index, record.frame, experience, offset, record.matched_robot,
                                   record.matched_frame, matched_experience, matched_offset,
                                   record.measurement if measured else "",
                                   (record.relative_pose.forward, record.relative_pose.left, record.relative_pose.yaw)
                                   if measured else (0.0, 0.0, 0.0), tuple(record.covariance) if measured else ())
            self.store.append(closure_record(closure))
            with self.lock:
                result = self.fleet.add_closure(closure)
            for decided in result.decided:
                if decided.fate != "pending":
                    log.info("fleetmap: closure %d of robot %s (frame %d ↔ robot %s frame %d): %s%s", decided.index,
                             decided.robot, decided.frame, decided.matched_robot, decided.matched_frame, decided.fate,
                             "" if decided.statistic is None else f" ({decided.statistic:.2f} std devs)")
            for name in result.joined:
                log.info("fleetmap: robot %s joined%s", name, " the fleet frame" if self.fleet.joined(name) else "")
            for pair in result.split:
                log.warning("fleetmap: robots %s and %s split apart: later closures contradict their join", *pair)
            self._after(result, None)
        if self.store.checkpoint_due():
            with self.lock:
                self.store.checkpoint(self.fleet)

    def _placement(self, robot: str, frame: int):
        """(experience, offset) of a robot's frame once its map has posed it (FramePlacements)."""
        feed = self.feeds.get(robot)
        state = self.fleet.robots.get(robot)
        if feed is None or state is None:
            return None
        found = feed.frames.find(frame, lambda first, last: self._query_frames(robot, first, last), time.monotonic())
        if found is None or found[0] >= len(state.poses):
            return None
        return found

    def _place_of(self, robot: str, frame: int):
        """A place's frame: it made an experience at that frame (a new view), else as any frame."""
        state = self.fleet.robots.get(robot)
        if state is None:
            return None
        index = bisect.bisect_left(state.created, frame)
        if index < len(state.created) and state.created[index] == frame:
            return index, (0.0, 0.0, 0.0)
        return self._placement(robot, frame)

    def _query_frames(self, robot: str, first: int, last: int) -> list | None:
        """The robot's map/frames from ``first`` to ``last``: (frame, experience, offset) rows, None
        without an answer."""
        rows = None
        for reply in self.session.get(f"{topics.key(robot, 'map/frames')}?from={first};to={last}", timeout=QUERY_TIMEOUT_S):
            if reply.ok is None:
                continue
            try:
                message = codec.decode(reply.ok.payload.to_bytes(), MapFrames, str(reply.ok.encoding))
            except codec.CodecError as error:
                log.warning("fleetmap: map/frames of robot %s: %s", robot, error)
                continue
            rows = (rows or []) + [(p.frame, p.experience, (p.dx, p.dy, p.dheading)) for p in message.frames]
        return rows

    # --- catching up -------------------------------------------------------------------------------
    def _maybe_sync(self) -> None:
        now = time.monotonic()
        if now < self.next_sync:
            return
        self.next_sync = now + self.config.sync_period
        for robot in sorted(self._live("expmap")):
            if robot not in self.fleet.robots or self._feed(robot).needs_snapshot or self._behind(robot):
                self._sync_robot(robot)
        for robot in sorted(self._live("loopclosure")):
            self._fetch_closures(robot)
        self._resolve()

    def _live(self, service: str) -> set[str]:
        robots = set()
        for reply in self.session.liveliness().get(topics.health_key("*", service, "*"), timeout=1.0):
            if reply.ok is not None:
                robots.add(topics.parse_health_key(str(reply.ok.key_expr))[0])
        return robots - {topics.FLEET}

    def _behind(self, robot: str) -> bool:
        """Whether the robot's expmap says its map has more than the fleet map holds (its last
        map/update lost, with no later one to show the gap)."""
        known, links = self._known(robot)
        return any(s.service == "expmap" and (s.extra.get("experiences", 0) > known or s.extra.get("links", 0) > links)
                   for s in health.statuses(self.session, robot, timeout=1.0))

    def _sync_robot(self, robot: str) -> None:
        """Take what the fleet map lacks of a robot's map from its map/snapshot."""
        snapshot = None
        for reply in self.session.get(topics.key(robot, "map/snapshot"), timeout=QUERY_TIMEOUT_S):
            if reply.ok is not None:
                try:
                    snapshot = codec.decode(reply.ok.payload.to_bytes(), MapSnapshot, str(reply.ok.encoding))
                except codec.CodecError as error:
                    log.warning("fleetmap: map/snapshot of robot %s: %s", robot, error)
        if snapshot is None:
            return
        feed = self._feed(robot)
        feed.needs_snapshot = False
        for e in snapshot.experiences:
            feed.poses[e.id] = (e.x, e.y, e.heading)
        known, links = self._known(robot)
        log.info("fleetmap: robot %s's map from its snapshot: experiences %d → %d, links %d → %d", robot, known,
                 len(snapshot.experiences), links, len(snapshot.links))
        increment = map_increment(known, links, snapshot.experiences, 0, snapshot.links)
        if increment is not None:
            self._grow(robot, *increment, snapshot.header)

    def _fetch_closures(self, robot: str) -> None:
        while True:
            got = None
            start = self.intake.next.get(robot, 0)
            for reply in self.session.get(f"{topics.key(robot, 'fleet/closures')}?from={start}",
                                          timeout=QUERY_TIMEOUT_S):
                if reply.ok is not None:
                    try:
                        got = codec.decode(reply.ok.payload.to_bytes(), FleetClosures, str(reply.ok.encoding))
                    except codec.CodecError as error:
                        log.warning("fleetmap: fleet/closures of robot %s: %s", robot, error)
            if got is None or not self.intake.take(robot, got.closures):
                return

    # --- outputs --------------------------------------------------------------------------------
    def _after(self, result: Result, header) -> None:
        self.changed.update(result.new)
        self.changed.update(result.moved)
        for closure in result.decided:
            self.decided[closure.ident] = closure
        if header is not None:
            self._last_header = header
        self._publish_update(force=bool(result.joined or result.split))

    def _robots(self) -> list[FleetRobot]:
        fleet = self.fleet
        return [FleetRobot(name=name, joined=fleet.joined(name), joined_at=fleet.joined_at.get(name),
                           part=fleet.part[name], experiences=len(state.poses)) for name, state in fleet.robots.items()]

    def _publish_update(self, force: bool = False) -> None:
        now = time.monotonic()
        if not (self.changed or self.decided) or (not force and now - self.last_update < UPDATE_PERIOD_S):
            return
        self.last_update = now
        fleet = self.fleet
        experiences = [FleetExperience(robot=robot, id=i, x=float(p[0]), y=float(p[1]), heading=float(p[2]))
                       for robot, i in sorted(self.changed) for p in [fleet.estimates[robot][i]]]
        links = [link_message(c) for c in self.decided.values()]
        self.changed, self.decided = set(), {}
        header = self.header(self._last_header.seq if self._last_header else 0, 0.0, "map")
        self._send("update", FleetUpdate(header=header, robots=self._robots(), experiences=experiences, links=links))
        self.counters.published += 1

    def snapshot(self) -> FleetSnapshot:
        """Called on a Zenoh thread: the whole fleet map, copied under the lock."""
        with self.lock:
            fleet = self.fleet
            robots = self._robots()
            experiences = [FleetExperience(robot=robot, id=i, x=float(x), y=float(y), heading=float(h))
                           for robot, poses in fleet.estimates.items() for i, (x, y, h) in enumerate(poses)]
            links = [link_message(c) for c in fleet.closures]
        return FleetSnapshot(header=self.header(0, 0.0, "map"), robots=robots, experiences=experiences, links=links)

    def extra_counters(self) -> dict[str, float]:
        counts = self.fleet.counts()
        return {**super().extra_counters(), "robots": len(self.fleet.robots),
                "robots_joined": sum(self.fleet.joined(r) for r in self.fleet.robots),
                "experiences": sum(len(s.poses) for s in self.fleet.robots.values()),
                **{f"closures_{fate}": count for fate, count in counts.items()},
                **{f"experiences_{robot}": len(state.poses) for robot, state in self.fleet.robots.items()},
                "closures_waiting": len(self.intake.waiting), "closures_duplicate": self.intake.duplicates}


def link_message(closure) -> FleetLink:
    return FleetLink(robot=closure.robot, index=closure.index, experience=closure.experience,
                     matched_robot=closure.matched_robot, matched_experience=closure.matched_experience, fate=closure.fate)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", help="fleet map parameters for a world: campus (its look-alikes)")
    parser.add_argument("--store", type=Path, help="journal of the fleet map's inputs (default fleet_map.log); a restart "
                                                   "resumes from it")
    parser.add_argument("--frame-robot", help=FleetMapConfig.model_fields["frame_robot"].description)


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    if args.robot not in (None, topics.FLEET):
        raise ConfigError(f"fleetmap serves the whole fleet under the key chunk {topics.FLEET!r}: leave --robot out "
                          f"(got {args.robot!r})")
    config = load_config(FleetMapConfig, "fleetmap", preset=args.preset, config_file=args.config,
                         overrides={"store": args.store, "frame_robot": args.frame_robot})
    return FleetMapService(runtime.model_copy(update={"robot": topics.FLEET}), config, args.instance).run()

