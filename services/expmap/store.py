"""Persistence of the experience map as an append-only log of its inputs.

The map is deterministic in its inputs (graph.py), so the log holds one record per frame —
odometry pose, view template, confirmed closure — and a restarted service rebuilds exactly the
map it had by replaying them. Each record is one line, `JSON<TAB>CRC32`, written and flushed
before the frame's pose is published, so a killed process leaves every published frame on
disk. A torn last record (the process died mid-write) is detected by its missing newline or
CRC, reported with a warning and cut off; a damaged record anywhere else is an error.
"""

from __future__ import annotations

import json
import logging
import os
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

from services.common.errors import DataError
from services.expmap.graph import ExperienceMap, MapParams

log = logging.getLogger(__name__)

FORMAT = "gridslam-experience-map"
VERSION = 1


class MapStoreError(DataError):
    """A map log that cannot be read or written (the message names the file and line)."""


@dataclass(frozen=True)
class Step:
    frame: int
    stamp: float
    odometry: tuple[float, float, float]
    template_id: int
    closure: tuple[int, int] | None     # (matched_template, matched_frame)

    def apply(self, experience_map: ExperienceMap):
        return experience_map.step(self.frame, self.odometry, self.template_id, self.closure)


def _line(record: dict) -> str:
    text = json.dumps(record, separators=(",", ":"), allow_nan=False)
    return f"{text}\t{zlib.crc32(text.encode()):08x}\n"


def _parse(line: str, path: Path, number: int) -> dict:
    text, tab, crc = line.rstrip("\n").rpartition("\t")
    if not tab or f"{zlib.crc32(text.encode()):08x}" != crc:
        raise MapStoreError(f"{path}: line {number}: record is damaged (checksum mismatch)")
    return json.loads(text)


class MapStore:
    """Opens (or creates) a map log; `steps` holds the records already there."""

    def __init__(self, path: Path, params: MapParams):
        self.path = Path(path)
        self.steps: list[Step] = []
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self.path.exists() and self.path.stat().st_size > 0:
                self._load(params)
            else:
                with open(self.path, "w") as handle:
                    handle.write(_line({"format": FORMAT, "version": VERSION, "params": asdict(params)}))
            self.handle = open(self.path, "a")
        except OSError as error:
            raise MapStoreError(f"{self.path}: cannot open the map log ({error.strerror})") from None

    def append(self, step: Step) -> None:
        record = {"frame": step.frame, "stamp": step.stamp, "odometry": list(step.odometry),
                  "template": step.template_id, "closure": list(step.closure) if step.closure else None}
        try:
            self.handle.write(_line(record))
            self.handle.flush()
        except OSError as error:
            raise MapStoreError(f"{self.path}: cannot append to the map log ({error.strerror})") from None
        self.steps.append(step)

    def close(self) -> None:
        try:
            self.handle.flush()
            os.fsync(self.handle.fileno())
        except OSError as error:
            log.error("%s: could not flush the map log: %s", self.path, error.strerror)
        finally:
            self.handle.close()

    def rebuild(self, params: MapParams) -> ExperienceMap:
        """The map the stored steps describe."""
        experience_map = ExperienceMap(params)
        for step in self.steps:
            step.apply(experience_map)
        return experience_map

    def _load(self, params: MapParams) -> None:
        with open(self.path) as handle:
            lines = handle.readlines()
        good = 0
        for number, line in enumerate(lines, start=1):
            last = number == len(lines)
            try:
                if not line.endswith("\n"):
                    raise MapStoreError(f"{self.path}: line {number}: record is torn (no end of line)")
                record = _parse(line, self.path, number)
            except (MapStoreError, json.JSONDecodeError) as error:
                if not last:
                    raise MapStoreError(str(error) if isinstance(error, MapStoreError)
                                        else f"{self.path}: line {number}: not JSON") from None
                log.warning("%s: line %d: torn last record skipped (a crash while writing): %s", self.path, number, error)
                break
            if number == 1:
                if record.get("format") != FORMAT:
                    raise MapStoreError(f"{self.path}: not a gridslam experience-map log")
                if record.get("params") != asdict(params):
                    raise MapStoreError(f"{self.path}: the map was built with parameters {record.get('params')}, "
                                        f"not {asdict(params)}; use another --store or the same parameters")
            else:
                closure = record["closure"]
                self.steps.append(Step(record["frame"], record["stamp"], tuple(record["odometry"]), record["template"],
                                       tuple(closure) if closure else None))
            good += len(line.encode())
        if good < self.path.stat().st_size:
            with open(self.path, "r+b") as handle:
                handle.truncate(good)
