"""Persistence of the experience map as an append-only journal of its inputs.

The map is deterministic in its inputs (graph.py), so the journal holds one record per frame —
odometry pose and the covariance of its increment, view template, confirmed closure with its
measurement — written before the frame's pose is published, and a restarted service rebuilds
exactly the map it had by replaying them (services/common/journal.py: one CRC-checked line per
record, torn last record cut off).

Replaying a long journal costs the whole run's map work again (minutes after hours of loops),
so the service also keeps a checkpoint next to it (`<journal>.checkpoint.npz`): when its
CheckpointPolicy says so (a rule on the map's own work, so two runs of the same inputs
checkpoint at the same frames and write the same journal) it appends a checkpoint record
(`{"checkpoint": n}`: the map was rebased after its first n steps, ExperienceMap.rebase),
rebases the map, and writes the state the rebase started from (temp file, then rename). A
restart restores that state and replays only the steps after it; a full replay rebases at the
same records, so both give the map the uninterrupted run had, bit for bit. The journal stays
the source of truth: a missing, damaged, stale (another journal's, or one cut shorter) or
parameter-mismatched checkpoint is skipped with a one-line warning naming it, and the whole
journal is replayed.
"""

from __future__ import annotations

import json
import logging
import os
import zipfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from services.common.journal import SESSION, Journal, JournalError
from services.expmap.graph import ExperienceMap, FrameResult, MapParams
from services.expmap.links import ClosureInput

log = logging.getLogger(__name__)

FORMAT = "gridslam-experience-map"
VERSION = 2
CHECKPOINT = "checkpoint"   # the journal record {"checkpoint": n}
CHECKPOINT_FORMAT = "gridslam-experience-map-checkpoint"
CHECKPOINT_VERSION = 1
EXTRA = "extra_"            # prefix of a checkpoint's arrays that are not the map's (the service's)


@dataclass(frozen=True)
class Step:
    frame: int
    stamp: float
    odometry: tuple[float, float, float]
    template_id: int
    closure: ClosureInput | None = None
    covariance: tuple[float, ...] | None = None   # of the odometry's increment since the previous frame
    earlier: tuple[ClosureInput, ...] = ()         # closures of earlier frames confirmed at this one

    def apply(self, experience_map: ExperienceMap) -> FrameResult:
        return experience_map.step(self.frame, self.odometry, self.template_id, self.closure, self.covariance,
                                   self.earlier)

    @property
    def closures(self) -> tuple[ClosureInput, ...]:
        """Every closure the step brings, its own first."""
        return ((self.closure,) if self.closure else ()) + self.earlier

    def record(self) -> dict:
        return {"frame": self.frame, "stamp": self.stamp, "odometry": list(self.odometry), "template": self.template_id,
                "closure": asdict(self.closure) if self.closure else None,
                "covariance": list(self.covariance) if self.covariance is not None else None,
                **({"earlier": [asdict(c) for c in self.earlier]} if self.earlier else {})}

    @classmethod
    def from_record(cls, record: dict) -> Step:
        """The step a journal record holds; KeyError, TypeError or ValueError when it holds none."""
        def closure_of(fields: dict) -> ClosureInput:
            return ClosureInput(**{**fields, "covariance": tuple(float(v) for v in fields["covariance"])})

        closure = record["closure"]
        covariance = record["covariance"]
        return cls(int(record["frame"]), float(record["stamp"]), tuple(float(v) for v in record["odometry"]),
                   int(record["template"]), closure_of(closure) if closure is not None else None,
                   tuple(float(v) for v in covariance) if covariance is not None else None,
                   tuple(closure_of(c) for c in record.get("earlier", ())))


def header(params: MapParams) -> dict:
    return {"format": FORMAT, "version": VERSION, "params": asdict(params)}


@dataclass(frozen=True)
class CheckpointPolicy:
    """When to checkpoint: once the optimiser has made `updates` updates since the last
    checkpoint, at least `min_steps` frames after it. An iSAM2 update costs time in proportion to
    the map (gtsam 4.3 visits the whole Bayes tree), and so does rebasing: on the looping stack's
    journal, rebasing 2800 experiences cost 0.9 s, about 230 of the updates around it
    (docs/reliability.md). 500 updates keep the replay after a restart to about two rebases'
    time and the rebases to about a third of the map's time. A map with few closures makes few
    updates and is not checkpointed: its frames are cheap, and replaying them costs about what
    rebuilding it from a checkpoint would (docs/reliability.md). `updates` 0: no checkpoints."""

    min_steps: int = 50
    updates: int = 500

    def due(self, experience_map: ExperienceMap, steps_since: int) -> bool:
        return 0 < self.updates <= experience_map.optimizer.updates and steps_since >= self.min_steps




def sessions_of(records: list[dict]) -> list[tuple[int, dict]]:
    """The session records of a journal's records (header excluded), each with the number of
    steps before it: the frames after it are that session's (services/common/layout.py)."""
    sessions, count = [], 0
    for record in records:
        if SESSION in record:
            sessions.append((count, record))
        elif CHECKPOINT not in record:
            count += 1
    return sessions


def parse_records(records: list[dict]) -> tuple[list[Step], list[int]]:
    """The steps of a journal's records (header excluded) and its checkpoints (how many steps
    each follows), its session records aside (sessions_of); ValueError naming the line of a
    record that is none of them."""
    steps, checkpoints = [], []
    for number, record in enumerate(records, start=2):
        try:
            if SESSION in record:
                continue
            if CHECKPOINT in record:
                if record[CHECKPOINT] != len(steps):
                    raise ValueError
                checkpoints.append(len(steps))
            else:
                steps.append(Step.from_record(record))
        except (KeyError, TypeError, ValueError, IndexError):
            raise ValueError(f"line {number}: not a map record") from None
    return steps, checkpoints


def checkpoint_path(journal: Path) -> Path:
    return journal.with_name(journal.name + ".checkpoint.npz")


def replay(experience_map: ExperienceMap, steps: list[Step], checkpoints: list[int], start: int = 0,
           each: Callable[[Step, FrameResult], None] | None = None, sessions: list[tuple[int, dict]] = ()) -> None:
    """Apply steps[start:], rebasing the map after each checkpoint's step as the live map was and
    starting each session where it began; `each` sees every step applied and its result."""
    marks = {n for n in checkpoints if n > start}
    begins = {index: record for index, record in sessions if index >= start}
    for index in range(start, len(steps) + 1):
        if index in begins:
            experience_map.start_session(localize=bool(begins[index].get("localize")))
        if index == len(steps):
            break
        result = steps[index].apply(experience_map)
        if each is not None:
            each(steps[index], result)
        if index + 1 in marks:
            experience_map.rebase()


def _checkpoint_meta(params: MapParams, steps: list[Step], count: int) -> dict:
    return json.loads(json.dumps({"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "params": asdict(params),
                                  "steps": count, "last": steps[count - 1].record()}))


def write_checkpoint(path: Path, meta: dict, state: dict[str, np.ndarray], extras: dict[str, np.ndarray]) -> None:
    """Write a checkpoint atomically (temp file, fsync, rename): a crash leaves the old one."""
    temporary = path.with_name(path.name + ".tmp")
    with open(temporary, "wb") as handle:
        np.savez(handle, meta=np.array(json.dumps(meta)), **state, **{EXTRA + k: v for k, v in extras.items()})
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)


def load_checkpoint(path: Path, params: MapParams, steps: list[Step], checkpoints: list[int]
                    ) -> tuple[ExperienceMap, int, dict[str, np.ndarray]] | None:
    """The map restored from the journal's checkpoint file, the steps it covers and the
    service's arrays saved with it; None, with a one-line warning, when there is no usable one."""
    file = checkpoint_path(path)
    whole = f"replaying the whole journal ({len(steps)} frames)"
    if not file.exists():
        if checkpoints:
            log.warning("%s: no map checkpoint (the journal has %d); %s", file, len(checkpoints), whole)
        return None
    try:
        with np.load(file, allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files}
        meta = json.loads(str(arrays.pop("meta")))
        if meta.get("format") != CHECKPOINT_FORMAT or meta.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"not a version {CHECKPOINT_VERSION} map checkpoint")
        count = meta["steps"]
        if meta["params"] != json.loads(json.dumps(asdict(params))):
            raise ValueError("written with other map parameters")
        if count not in checkpoints or meta != _checkpoint_meta(params, steps, count):
            raise ValueError(f"stale: its checkpoint after step {count} is not this journal's")
        extras = {name[len(EXTRA):]: arrays.pop(name) for name in list(arrays) if name.startswith(EXTRA)}
        return ExperienceMap.restore(params, arrays), count, extras
    except (OSError, EOFError, zipfile.BadZipFile, KeyError, TypeError, ValueError, IndexError, RuntimeError) as error:
        log.warning("%s: unusable map checkpoint (%s); %s", file, str(error).strip("'") or type(error).__name__, whole)
        return None


def rebuild(path: Path, params: MapParams, steps: list[Step], checkpoints: list[int],
            each: Callable[[Step, FrameResult], None] | None = None, sessions: list[tuple[int, dict]] = ()
            ) -> tuple[ExperienceMap, int, dict[str, np.ndarray]]:
    """The map a journal describes: from its checkpoint and the steps after it when there is a
    usable one, else from all its steps; how many steps the checkpoint covered (0: none); the
    service's arrays the checkpoint holds. `each` sees each step replayed."""
    restored = load_checkpoint(Path(path), params, steps, checkpoints)
    experience_map, start, extras = restored if restored is not None else (ExperienceMap(params), 0, {})
    replay(experience_map, steps, checkpoints, start, each, sessions)
    return experience_map, start, extras


class MapStore:
    """The map's journal; `steps` holds the frames already in it, `checkpoints` after how many
    steps the map was rebased."""

    def __init__(self, path: Path, params: MapParams, policy: CheckpointPolicy = CheckpointPolicy()):
        self.path, self.params, self.policy = Path(path), params, policy
        self.journal = Journal(path, header(params))
        try:
            self.steps, self.checkpoints = parse_records(self.journal.records)
            self.sessions = sessions_of(self.journal.records)
        except ValueError as error:
            self.journal.close()
            raise JournalError(f"{self.path}: {error}") from None

    def append(self, step: Step) -> None:
        self.journal.append(step.record())
        self.steps.append(step)

    def checkpoint_due(self, experience_map: ExperienceMap) -> bool:
        return self.policy.due(experience_map, len(self.steps) - (self.checkpoints[-1] if self.checkpoints else 0))

    def checkpoint(self, experience_map: ExperienceMap) -> tuple[dict, dict[str, np.ndarray]]:
        """Record a checkpoint after the steps so far and rebase the map there (the record first:
        what follows is computed on the rebased map). The meta data and state `write_checkpoint`
        takes; the caller writes them, off its hot path if it likes."""
        if not self.steps:
            raise ValueError("a checkpoint needs a step before it")
        self.journal.append({CHECKPOINT: len(self.steps)})
        self.checkpoints.append(len(self.steps))
        return _checkpoint_meta(self.params, self.steps, len(self.steps)), experience_map.rebase()

    def write_checkpoint(self, meta: dict, state: dict[str, np.ndarray], extras: dict[str, np.ndarray]) -> None:
        write_checkpoint(checkpoint_path(self.path), meta, state, extras)

    def close(self) -> None:
        self.journal.close()

    def rebuild(self, each: Callable[[Step, FrameResult], None] | None = None
                ) -> tuple[ExperienceMap, int, dict[str, np.ndarray]]:
        """The map the stored steps describe (from the checkpoint when usable), the steps the
        checkpoint covered, and the arrays the service saved with it."""
        return rebuild(self.path, self.params, self.steps, self.checkpoints, each, self.sessions)
