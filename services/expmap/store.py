"""Persistence of the experience map as an append-only journal of its inputs.

The map is deterministic in its inputs (graph.py), so the journal holds one record per frame —
odometry pose, view template, confirmed closure — written before the frame's pose is published,
and a restarted service rebuilds exactly the map it had by replaying them
(services/common/journal.py: one CRC-checked line per record, torn last record cut off).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from services.common.journal import Journal
from services.expmap.graph import ExperienceMap, FrameResult, MapParams

FORMAT = "gridslam-experience-map"
VERSION = 1


@dataclass(frozen=True)
class Step:
    frame: int
    stamp: float
    odometry: tuple[float, float, float]
    template_id: int
    closure: tuple[int, int] | None     # (matched_template, matched_frame)

    def apply(self, experience_map: ExperienceMap) -> FrameResult:
        return experience_map.step(self.frame, self.odometry, self.template_id, self.closure)


class MapStore:
    """The map's journal; `steps` holds the frames already in it."""

    def __init__(self, path: Path, params: MapParams):
        self.journal = Journal(path, {"format": FORMAT, "version": VERSION, "params": asdict(params)})
        self.steps = [Step(r["frame"], r["stamp"], tuple(r["odometry"]), r["template"],
                           tuple(r["closure"]) if r["closure"] else None) for r in self.journal.records]

    def append(self, step: Step) -> None:
        self.journal.append({"frame": step.frame, "stamp": step.stamp, "odometry": list(step.odometry),
                             "template": step.template_id, "closure": list(step.closure) if step.closure else None})
        self.steps.append(step)

    def close(self) -> None:
        self.journal.close()

    def rebuild(self, params: MapParams) -> ExperienceMap:
        """The map the stored steps describe."""
        experience_map = ExperienceMap(params)
        for step in self.steps:
            step.apply(experience_map)
        return experience_map
