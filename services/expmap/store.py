"""Persistence of the experience map as an append-only journal of its inputs.

The map is deterministic in its inputs (graph.py), so the journal holds one record per frame —
odometry pose and the covariance of its increment, view template, confirmed closure with its
measurement — written before the frame's pose is published, and a restarted service rebuilds
exactly the map it had by replaying them (services/common/journal.py: one CRC-checked line per
record, torn last record cut off).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from services.common.journal import Journal
from services.expmap.graph import ClosureInput, ExperienceMap, FrameResult, MapParams

FORMAT = "gridslam-experience-map"
VERSION = 2


@dataclass(frozen=True)
class Step:
    frame: int
    stamp: float
    odometry: tuple[float, float, float]
    template_id: int
    closure: ClosureInput | None = None
    covariance: tuple[float, ...] | None = None   # of the odometry's increment since the previous frame

    def apply(self, experience_map: ExperienceMap) -> FrameResult:
        return experience_map.step(self.frame, self.odometry, self.template_id, self.closure, self.covariance)

    def record(self) -> dict:
        return {"frame": self.frame, "stamp": self.stamp, "odometry": list(self.odometry), "template": self.template_id,
                "closure": asdict(self.closure) if self.closure else None,
                "covariance": list(self.covariance) if self.covariance is not None else None}

    @classmethod
    def from_record(cls, record: dict) -> Step:
        """The step a journal record holds; KeyError, TypeError or ValueError when it holds none."""
        closure = record["closure"]
        if closure is not None:
            closure = ClosureInput(**{**closure, "covariance": tuple(float(v) for v in closure["covariance"])})
        covariance = record["covariance"]
        return cls(int(record["frame"]), float(record["stamp"]), tuple(float(v) for v in record["odometry"]),
                   int(record["template"]), closure, tuple(float(v) for v in covariance) if covariance is not None else None)


def header(params: MapParams) -> dict:
    return {"format": FORMAT, "version": VERSION, "params": asdict(params)}


class MapStore:
    """The map's journal; `steps` holds the frames already in it."""

    def __init__(self, path: Path, params: MapParams):
        self.journal = Journal(path, header(params))
        self.steps = [Step.from_record(r) for r in self.journal.records]

    def append(self, step: Step) -> None:
        self.journal.append(step.record())
        self.steps.append(step)

    def close(self) -> None:
        self.journal.close()

    def rebuild(self, params: MapParams) -> ExperienceMap:
        """The map the stored steps describe."""
        experience_map = ExperienceMap(params)
        for step in self.steps:
            step.apply(experience_map)
        return experience_map
