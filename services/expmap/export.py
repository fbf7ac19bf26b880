"""Export of a persisted experience map: the graph (experiences and links) as JSON and the
corrected per-frame trajectory in TUM format.

The map log (store.py) holds the map's inputs, not its state, so an export replays them (after
the log's checkpoint, when it has a usable one) with the parameters the log was written with
and reads the result off the rebuilt map. The log is only read here, never cut: a service may
still be appending to it, and a torn last record (a write in progress, or a crash) is skipped
with a warning exactly as a restart would skip it.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from services.common.errors import DataError
from services.common.journal import read_records
from services.evaluation import metrics
from services.evaluation.results import write_json
from services.evaluation.trajectory import Trajectory, write_tum
from services.expmap.graph import ExperienceMap, MapParams
from services.expmap.store import (
    FORMAT,
    VERSION,
    Step,
    parse_records,
    rebuild,
    sessions_of,
)

log = logging.getLogger(__name__)

GRAPH_FORMAT = "gridslam-experience-graph"
GRAPH_VERSION = 3   # 3: parts of the graph (sessions)


class MapExportError(DataError):
    """A map that cannot be exported (the message names the file)."""


@dataclass(frozen=True, eq=False)
class MapLog:
    """What a map log holds: the parameters it was written with and its frames' inputs."""

    path: Path
    params: MapParams
    steps: list[Step]
    torn_last_record: bool = False
    checkpoints: list[int] = field(default_factory=list)   # after how many steps the map was rebased
    sessions: list[tuple[int, dict]] = field(default_factory=list)   # where each later session began

    def rebuild(self) -> ExperienceMap:
        """The map: from the log's checkpoint file and the steps after it, or from all its steps."""
        return rebuild(self.path, self.params, self.steps, self.checkpoints, sessions=self.sessions)[0]


def read_log(path, params: MapParams | None = None) -> MapLog:
    """Read a map log without changing it (its format: services/common/journal.py). `params`
    None takes the log's own parameters; otherwise they must equal the log's (the same inputs
    replayed with other parameters make another map)."""
    path = Path(path)
    if not path.is_file():
        raise MapExportError(f"{path}: no such map log")
    records, _, torn = read_records(path)
    if not records or records[0].get("format") != FORMAT or not isinstance(records[0].get("params"), dict):
        raise MapExportError(f"{path}: not a gridslam experience-map log")
    try:
        logged = MapParams(**records[0]["params"])
    except TypeError:
        raise MapExportError(f"{path}: line 1: unknown map parameters {records[0]['params']}") from None
    if params is not None and params != logged:
        raise MapExportError(f"{path}: the map was built with parameters {asdict(logged)}, not {asdict(params)}; "
                             "export it with the same preset or config (or with neither: the log's own)")
    if records[0].get("version") != VERSION:
        raise MapExportError(f"{path}: a version {records[0].get('version')} map log; this gridslam reads version {VERSION}")
    try:
        steps, checkpoints = parse_records(records[1:])
    except ValueError as error:
        raise MapExportError(f"{path}: {error}") from None
    return MapLog(path, logged, steps, torn, checkpoints, sessions_of(records[1:]))


def graph_dict(experience_map: ExperienceMap) -> dict:
    """The map as a graph: experiences (final map pose, template, frame of creation, the part of
    the graph it is in: 0 for the map's frame, another for a later session no closure joined to
    it yet, whose poses are then in its own frame) and links (transform from source to target,
    the frame that made it, loop_closure, and accepted: false for a closure the map refused);
    `parts` lists the parts, `connected` says whether there is just one."""
    poses = experience_map.final_poses()
    return {
        "format": GRAPH_FORMAT,
        "version": GRAPH_VERSION,
        "params": asdict(experience_map.params),
        "frames": len(experience_map.frames),
        "parts": sorted(experience_map.anchors),
        "connected": len(experience_map.anchors) == 1,
        "experiences": [{"id": i, "x": float(x), "y": float(y), "heading": float(heading),
                         "template_id": experience_map.templates[i], "frame": experience_map.created[i],
                         "part": experience_map.parts[i]}
                        for i, (x, y, heading) in enumerate(poses)],
        "links": [asdict(link) for link in experience_map.links],
    }


def corrected_trajectory(experience_map: ExperienceMap, steps: list[Step]) -> Trajectory:
    """Every frame placed on the relaxed map (ExperienceMap.trajectory), stamped from the log."""
    stamps = {step.frame: step.stamp for step in steps}
    rows = experience_map.trajectory()
    if not rows:
        return Trajectory.from_planar([], [], [], [])
    frames, x, y, heading = (np.array(column) for column in zip(*rows))
    return Trajectory.from_planar([stamps[int(f)] for f in frames], x, y, heading)


def odometry_trajectory(steps: list[Step]) -> Trajectory:
    """The map's input odometry (uncorrected), same frames and stamps."""
    if not steps:
        return Trajectory.from_planar([], [], [], [])
    odometry = np.array([step.odometry for step in steps])
    return Trajectory.from_planar([step.stamp for step in steps], odometry[:, 0], odometry[:, 1], odometry[:, 2])


@dataclass
class ExportResult:
    map_log: MapLog
    experience_map: ExperienceMap
    files: dict[str, Path] = field(default_factory=dict)

    def summary(self) -> dict:
        links = self.experience_map.links
        return {"frames": len(self.map_log.steps), "experiences": len(self.experience_map), "links": len(links),
                "loop_closure_links": sum(link.loop_closure for link in links),
                "sessions": 1 + len(self.map_log.sessions), "parts": len(self.experience_map.anchors),
                "torn_last_record": self.map_log.torn_last_record}


def errors_against(map_log: MapLog, experience_map: ExperienceMap, reference: Trajectory) -> dict:
    """Position errors (m: mean, max, rmse) of the map's input odometry and of its corrected
    trajectory against a reference (ground truth), poses paired by stamp; both as they are
    ("none": the same start, the map's frame is the odometry's) and SE(2)-aligned."""
    result = {}
    for name, traj in (("odometry", odometry_trajectory(map_log.steps)),
                       ("corrected", corrected_trajectory(experience_map, map_log.steps))):
        estimate, truth = metrics.associate(traj, reference)
        result[name] = {"poses": len(estimate)}
        for kind in ("none", "se2"):
            errors = metrics.position_errors(estimate, truth, align=kind)
            result[name][kind] = {"mean": float(errors.mean()), "max": float(errors.max()),
                                  "rmse": float(np.sqrt(np.mean(errors ** 2)))}
    return result


def export_map(store, graph: Path | None = None, tum: Path | None = None, params: MapParams | None = None) -> ExportResult:
    """Rebuild the map of `store` and write the graph JSON and/or the corrected TUM trajectory."""
    map_log = read_log(store, params)
    experience_map = map_log.rebuild()
    result = ExportResult(map_log, experience_map)
    try:
        if graph is not None:
            result.files["graph"] = write_json(graph, graph_dict(experience_map))
        if tum is not None:
            result.files["tum"] = write_tum(tum, corrected_trajectory(experience_map, map_log.steps))
    except OSError as error:
        raise MapExportError(f"cannot write the export ({error.strerror or error})") from None
    return result
