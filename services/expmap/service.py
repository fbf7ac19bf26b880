"""expmap: the RatSLAM experience map of grid-cell odometry, view templates and loop closures."""

from __future__ import annotations

import argparse
import collections
import logging
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

from schemas import Experience, GridPose, Link, LoopClosure, MapPose, MapSnapshot, MapUpdate, ViewTemplate
from services.common.config import load_config
from services.common.convert import planar_pose
from services.common.errors import DataError
from services.common.runtime import RuntimeConfig
from services.common.service import REPLAY_FRAMES, Service
from services.expmap.graph import ExperienceMap, FrameResult, MapParams
from services.expmap.store import MapStore, Step

log = logging.getLogger(__name__)

# Odometry beyond these is no robot's (10,000 km; a million radians of accumulated turning): such
# a pose would overflow the map's arithmetic after it was journaled, so it is rejected before.
MAX_COORDINATE_M = 1e7
MAX_HEADING_RAD = 1e6


class MapInputError(DataError):
    """A grid pose the map cannot take (the message says which value)."""


class ExpMapConfig(BaseModel):
    """Configuration of the expmap service (table `[expmap]`, env `GRIDSLAM_EXPMAP_*`, presets)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    new_experience_distance: float = Field(1.0, gt=0, description="Metres of odometry before a new experience.")
    correction: float = Field(0.5, gt=0, le=1, description="Relaxation correction factor (RatSLAM: 0.5).")
    relax_passes: int = Field(10, ge=0, description="Relaxation passes on a frame with a loop closure.")
    relax_every_frame: int = Field(1, ge=0, description="Relaxation passes on every other frame.")
    store: Path = Field(Path("experience_map.log"), description="Append-only map log; a restart resumes from it.")

    def params(self) -> MapParams:
        return MapParams(new_experience_distance=self.new_experience_distance, correction=self.correction,
                         relax_passes=self.relax_passes, relax_every_frame=self.relax_every_frame)


def experience_message(experience_map: ExperienceMap, index: int) -> Experience:
    x, y, heading = experience_map.poses[index]
    return Experience(id=index, x=float(x), y=float(y), heading=float(heading),
                      template_id=experience_map.templates[index], frame=experience_map.created[index])


def link_message(link) -> Link:
    return Link(source=link.source, target=link.target, dx=link.dx, dy=link.dy, dheading=link.dheading,
                frame=link.frame, loop_closure=link.loop_closure)


class ExpMapService(Service):
    name = "expmap"

    def __init__(self, runtime: RuntimeConfig, config: ExpMapConfig, instance: str | None = None):
        super().__init__(runtime, instance)
        self.config = config
        self.store = MapStore(config.store, config.params())
        self.map = ExperienceMap(config.params())
        # Results of the last frames, to answer a re-sent frame that is already in the map.
        self.recent: collections.OrderedDict[int, FrameResult] = collections.OrderedDict()
        for step in self.store.steps:
            self._remember(step.apply(self.map))
        if self.store.steps:
            log.info("expmap resumed from %s: %d frames, %d experiences, %d links", config.store,
                     len(self.store.steps), len(self.map), len(self.map.links))
        self.poses: dict[int, GridPose] = {}
        self.views: dict[int, ViewTemplate] = {}
        self.closures: dict[int, LoopClosure] = {}
        self.skipped = 0   # frames with a pose but no view template

    def setup(self) -> None:
        self.subscribe("grid/pose", self.on_grid_pose)
        self.subscribe("view/template", self.on_view)
        self.subscribe("loop/closure", self.on_closure, sparse=True)
        self.queryable("map/snapshot", self.snapshot)

    def teardown(self) -> None:
        self.store.close()

    def on_grid_pose(self, message: GridPose) -> None:
        position = message.pose.position
        if max(abs(position.x), abs(position.y)) > MAX_COORDINATE_M or abs(message.heading) > MAX_HEADING_RAD:
            raise MapInputError(f"grid pose ({position.x:.3g}, {position.y:.3g}) m, heading {message.heading:.3g} rad "
                                f"is beyond {MAX_COORDINATE_M:g} m or {MAX_HEADING_RAD:g} rad")
        self.poses[message.header.seq] = message
        self._advance()

    def on_view(self, message: ViewTemplate) -> None:
        self.views[message.header.seq] = message
        self._advance()

    def on_closure(self, message: LoopClosure) -> None:
        self.closures[message.header.seq] = message
        self._advance()

    def _advance(self) -> None:
        """Apply every frame whose inputs are all in, in frame order (the map is deterministic in
        its input order, whatever order the topics' messages arrive in)."""
        while self.poses:
            seq = min(self.poses)
            view = self.views.get(seq)
            if view is None and any(s > seq for s in self.views):
                # Views come in frame order, so this frame's never will (loopclosure rejected it):
                # skip it rather than hold every later frame behind it.
                self.poses.pop(seq)
                self.skipped += 1
                log.warning("expmap: frame %d skipped: no view template for it, later ones arrived", seq)
                continue
            if view is None or (view.loop_closure and seq not in self.closures):
                return
            pose = self.poses.pop(seq)
            self.views.pop(seq)
            closure = self.closures.pop(seq, None)
            for stale in [s for s in self.views if s < seq]:
                del self.views[stale]
            if self.map.last_frame is not None and seq <= self.map.last_frame:
                if seq in self.recent:   # already in the map (a re-sent frame after a restart): answer again
                    self._publish_pose(pose, self.recent[seq])
                continue
            step = Step(seq, pose.header.stamp.to_seconds(), (pose.pose.position.x, pose.pose.position.y, pose.heading),
                        view.template_id, (closure.matched_template, closure.matched_frame) if closure else None)
            self.store.append(step)   # on disk before anything is published
            result = step.apply(self.map)
            self._remember(result)
            self._publish(pose, result)

    def _publish(self, pose: GridPose, result: FrameResult) -> None:
        if result.new_experiences or result.new_links or result.moved:
            changed = sorted(set(result.new_experiences) | set(result.moved))
            self.publish("map/update", MapUpdate(
                header=pose.header.model_copy(update={"frame_id": "map"}),
                experiences=[experience_message(self.map, i) for i in changed],
                links=[link_message(link) for link in result.new_links],
                experience_count=len(self.map), link_count=len(self.map.links)))
        self._publish_pose(pose, result)

    def _publish_pose(self, pose: GridPose, result: FrameResult) -> None:
        x, y, heading = result.pose
        self.publish("map/pose", MapPose(header=pose.header.model_copy(update={"frame_id": "map"}),
                                         pose=planar_pose(x, y, heading), heading=heading,
                                         experience_id=result.experience))

    def _remember(self, result: FrameResult) -> None:
        self.recent[result.frame] = result
        while len(self.recent) > REPLAY_FRAMES:
            self.recent.popitem(last=False)

    def snapshot(self) -> MapSnapshot:
        # Called on a Zenoh thread: read a consistent copy (lists are only appended to).
        count, links = len(self.map), list(self.map.links)
        last = self.map.last_frame or 0
        return MapSnapshot(header=self.header(last, 0.0, "map"),
                           experiences=[experience_message(self.map, i) for i in range(count)],
                           links=[link_message(link) for link in links])

    def extra_counters(self) -> dict[str, float]:
        return {**super().extra_counters(), "experiences": len(self.map), "links": len(self.map.links),
                "frames_in_map": len(self.map.frames), "frames_skipped": self.skipped}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", help="map parameters for a dataset: synthetic, nubot, kitti, stlucia")
    parser.add_argument("--store", type=Path, help="map log file (default experience_map.log); a restart resumes from it")


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    config = load_config(ExpMapConfig, "expmap", preset=args.preset, config_file=args.config,
                         overrides={"store": args.store})
    return ExpMapService(runtime, config, args.instance).run()
