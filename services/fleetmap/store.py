"""Persistence of the fleet map: an append-only journal of its inputs (services/common/journal.py)
and a checkpoint beside it, as the experience map keeps its own (services/expmap/store.py).

The fleet map is deterministic in the order of its inputs (graph.py), so the journal holds one
record per input, in the order the service applied them — a robot's map grown
(`{"map": robot, "experiences", "links"}`) or an inter-robot closure placed on both maps
(`{"closure": {...}}`) — written before anything derived from it is published, and a restarted
service rebuilds the same map by replaying them. Every `checkpoint_events` inputs it appends a
checkpoint record (`{"checkpoint": n}`), rebases the map (FleetMap.rebase) and writes the state the
rebase started from to `<journal>.checkpoint.json` (temp file, then rename); a restart restores it
and replays only the inputs after it. A missing, stale or damaged checkpoint is skipped with a
one-line warning, and the whole journal replayed.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import asdict
from pathlib import Path

from services.common.journal import Journal, JournalError, read_records
from services.fleetmap.consistency import ConsistencyParams
from services.fleetmap.graph import ClosureInput, FleetMap, FleetParams, Result

log = logging.getLogger(__name__)

FORMAT = "gridslam-fleet-map"
VERSION = 1
CHECKPOINT = "checkpoint"
CHECKPOINT_FORMAT = "gridslam-fleet-map-checkpoint"


def header(params: FleetParams, consistency: ConsistencyParams) -> dict:
    return json.loads(json.dumps({"format": FORMAT, "version": VERSION, "params": asdict(params),
                                  "consistency": asdict(consistency)}))


def map_record(robot: str, experiences: list, links: list) -> dict:
    return {"map": robot, "experiences": [list(e) for e in experiences],
            "links": [[*link[:7], [float(v) for v in link[7]]] for link in links]}


def closure_record(closure: ClosureInput) -> dict:
    return {"closure": asdict(closure)}


def apply(fleet: FleetMap, record: dict) -> Result:
    """Apply one journal record to the map; ValueError for a record that is neither input."""
    if "map" in record:
        return fleet.add_map(record["map"], [tuple(e) for e in record["experiences"]],
                             [(int(s), int(t), dx, dy, dh, bool(c), bool(a), cov)
                              for s, t, dx, dy, dh, c, a, cov in record["links"]])
    if "closure" in record:
        fields = record["closure"]
        return fleet.add_closure(ClosureInput(**{**fields, "offset": tuple(fields["offset"]),
                                                 "matched_offset": tuple(fields["matched_offset"]),
                                                 "relative_pose": tuple(fields["relative_pose"]),
                                                 "covariance": tuple(fields["covariance"])}))
    raise ValueError("not a fleet map record")


def checkpoint_path(journal: Path) -> Path:
    return journal.with_name(journal.name + ".checkpoint.json")


class FleetStore:
    """The fleet map's journal; `inputs` holds the inputs in it, `checkpoints` after how many inputs
    the map was rebased."""

    def __init__(self, path: Path, params: FleetParams, consistency: ConsistencyParams, checkpoint_events: int = 2000):
        self.path, self.params, self.consistency = Path(path), params, consistency
        self.checkpoint_events = checkpoint_events
        self.journal = Journal(self.path, header(params, consistency))
        self.inputs: list[dict] = []
        self.checkpoints: list[int] = []
        for number, record in enumerate(self.journal.records, start=2):
            if CHECKPOINT in record:
                if record[CHECKPOINT] != len(self.inputs):
                    self.journal.close()
                    raise JournalError(f"{self.path}: line {number}: not a fleet map record")
                self.checkpoints.append(len(self.inputs))
            elif "map" in record or "closure" in record:
                self.inputs.append(record)
            else:
                self.journal.close()
                raise JournalError(f"{self.path}: line {number}: not a fleet map record")

    def append(self, record: dict) -> None:
        self.journal.append(record)
        self.inputs.append(record)

    def checkpoint_due(self) -> bool:
        since = len(self.inputs) - (self.checkpoints[-1] if self.checkpoints else 0)
        return 0 < self.checkpoint_events <= since

    def checkpoint(self, fleet: FleetMap) -> None:
        """Record a checkpoint after the inputs so far, rebase the map there, write its state."""
        self.journal.append({CHECKPOINT: len(self.inputs)})
        self.checkpoints.append(len(self.inputs))
        state = fleet.rebase()
        meta = {"format": CHECKPOINT_FORMAT, "version": VERSION, "header": header(self.params, self.consistency),
                "inputs": len(self.inputs), "last": self.inputs[-1]}
        temporary = checkpoint_path(self.path).with_suffix(".tmp")
        try:
            with open(temporary, "w") as handle:
                json.dump({"meta": meta, "state": state}, handle)
                handle.flush()
                os.fsync(handle.fileno())
            os.replace(temporary, checkpoint_path(self.path))
        except OSError as error:   # the journal still holds the map: a restart replays more of it
            log.warning("%s: cannot write the fleet map checkpoint (%s)", self.path, error.strerror or error)

    def rebuild(self, each=None) -> tuple[FleetMap, int]:
        """The map the journal describes (from its checkpoint when usable) and how many inputs the
        checkpoint covered; ``each(record, result)`` sees every input replayed."""
        fleet, start = self._restored() or (FleetMap(self.params, self.consistency), 0)
        marks = {n for n in self.checkpoints if n > start}
        for index in range(start, len(self.inputs)):
            result = apply(fleet, self.inputs[index])
            if each is not None:
                each(self.inputs[index], result)
            if index + 1 in marks:
                fleet.rebase()
        return fleet, start

    def _restored(self) -> tuple[FleetMap, int] | None:
        file = checkpoint_path(self.path)
        if not file.exists():
            return None
        try:
            saved = json.loads(file.read_text())
            meta, count = saved["meta"], saved["meta"]["inputs"]
            if meta["header"] != header(self.params, self.consistency):
                raise ValueError("written with other parameters")
            if count not in self.checkpoints or meta["last"] != self.inputs[count - 1]:
                raise ValueError(f"stale: its checkpoint after input {count} is not this journal's")
            return FleetMap.restore(self.params, self.consistency, saved["state"]), count
        except (OSError, KeyError, TypeError, ValueError, IndexError) as error:
            log.warning("%s: unusable fleet map checkpoint (%s); replaying the whole journal (%d inputs)", file,
                        str(error).strip("'") or type(error).__name__, len(self.inputs))
            return None

    def close(self) -> None:
        self.journal.close()


def read_fleet_log(path: Path, params: FleetParams | None = None, consistency: ConsistencyParams | None = None
                   ) -> FleetMap:
    """The fleet map a journal holds, rebuilt with the parameters it was written with, read only."""
    records, _, _ = read_records(Path(path))
    if not records or records[0].get("format") != FORMAT:
        raise JournalError(f"{path}: not a {FORMAT} journal")
    params = params or FleetParams(**records[0]["params"])
    consistency = consistency or ConsistencyParams(**records[0]["consistency"])
    fleet = FleetMap(params, consistency)
    inputs = [record for record in records[1:] if CHECKPOINT not in record]
    marks, count = set(), 0
    for record in records[1:]:
        if CHECKPOINT in record:
            marks.add(count)
        else:
            count += 1
    for index, record in enumerate(inputs):
        apply(fleet, record)
        if index + 1 in marks:
            fleet.rebase()
    return fleet
