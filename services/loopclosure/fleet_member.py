"""The loopclosure service's part in a fleet (docs/fleet.md), a thin adapter around
services/loopclosure/fleet.py.

- Its own new places go out on `<robot>/fleet/place` (PlaceRecord: the keyframe's bytes, never an
  image), and its queryable `<robot>/fleet/places?from=N` answers the places from id N on.
- The other robots' places come in on `*/fleet/place`; each is learnt once (FleetRecognition.add),
  journaled beside the service's own journal (`<store>.fleet.log`, its keyframes in
  `<store>.fleet.keyframes`), so a restart learns them again from disk.
- No place is lost: every `sync_period` seconds, and at once when a place arrives with an id
  beyond the next one expected, it asks every live robot's loopclosure (their health tokens)
  for its places from the first one it lacks. A robot that joins late, a service restarted, a
  network partition healed: each catches up this way.
- The inter-robot closures it confirms go out on `<robot>/fleet/closure`, numbered from 0, and the
  queryable `<robot>/fleet/closures?from=N` answers them again (the fleet map catches up so).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh

from schemas import FleetClosureRecord, FleetClosures, FleetPlaces, PlaceRecord, PlanarIncrement
from services.common import codec, topics
from services.common.errors import ConfigError
from services.common.journal import Journal
from services.common.settings import params_of, setting
from services.loopclosure.detector import MemoryKeyframes
from services.loopclosure.fleet import FleetConfirmed, FleetParams, FleetRecognition, vote_of, vote_record
from services.loopclosure.geometry import Keyframe, KeyframeError
from services.loopclosure.keyframes import KeyframeStore
from services.loopclosure.vocabulary import Vocabulary, default_vocabulary

log = logging.getLogger(__name__)

PLACES_FORMAT = "gridslam-fleet-places"
PLACES_VERSION = 1
REPLY_PLACES = 32          # places per fleet/places reply (the asker asks again from the next)
REPLY_CLOSURES = 256       # closures per fleet/closures reply
QUERY_TIMEOUT_S = 2.0


@dataclass(frozen=True)
class FleetSyncParams:
    LABEL = "fleet places"

    sync_period: float = setting(3.0, gt=0, help="Seconds between asking the live robots for the places this one lacks.")


def parse_from(text: str | None, name: str = "from") -> int:
    try:
        value = int(text or "0")
    except ValueError:
        raise ConfigError(f"fleet: parameter {name!r} must be a non-negative integer, got {text!r}") from None
    if value < 0:
        raise ConfigError(f"fleet: parameter {name!r} must be a non-negative integer, got {text!r}")
    return value


class FleetMember:
    def __init__(self, service, config):
        self.service = service
        self.robot = service.robot
        if service.detector.mode != "auto":
            raise ConfigError("[loopclosure] fleet: inter-robot closures need the places' keyframes and their geometry "
                              "(geometry = \"auto\", closure = \"metric\")")
        params = params_of(FleetParams, config, "fleet_")
        params.check()
        self.sync = params_of(FleetSyncParams, config, "fleet_")
        vocabulary = Vocabulary.load(Path(config.bow_vocabulary)) if config.bow_vocabulary else default_vocabulary()
        self.journal = None
        if config.store is not None:
            keyframes = KeyframeStore(config.store.with_suffix(".fleet.keyframes"), int(config.keyframe_store_mb * 2**20))
        else:
            keyframes = MemoryKeyframes(limit=1 << 30)
        self.recognition = FleetRecognition(vocabulary, params, service.detector.geometry, keyframes)
        if config.store is not None:
            self.journal = Journal(config.store.with_suffix(".fleet.log"), {"format": PLACES_FORMAT, "version": PLACES_VERSION})
            for number, record in enumerate(self.journal.records, start=2):
                keyframe = keyframes.get(number - 2)
                if keyframe is None:   # its keyframe never reached the disk: asked for again at the next sync
                    break
                self.recognition.add(record["robot"], int(record["place"]), int(record["frame"]), keyframe, store=False)
            keyframes.truncate(len(self.recognition))
        self.own: dict[int, int] = {}       # this robot's places: id → frame
        self.listeners: set[str] = set()    # the other robots' loopclosures alive (their health tokens)
        self.lock = service.lock            # the queryables read the keyframes the main thread writes
        self.next_sync = 0.0
        self.counters = {"fleet_places_sent": 0, "fleet_places_resent": 0, "fleet_places_unheard": 0, "fleet_bytes_sent": 0, "fleet_places_learnt": 0,
                         "fleet_places_refused": 0, "fleet_bytes_received": 0, "fleet_closures": 0, "camera_bytes": 0}

    # --- wiring -----------------------------------------------------------------------------------
    def setup(self) -> None:
        s = self.service
        s.subscribe("fleet/place", self.on_place, robot="*", sparse=True, drop_stale=False)
        s.queryable("fleet/places", self.places_reply, parameters=True)
        s.queryable("fleet/closures", self.closures_reply, parameters=True)
        s.watch(topics.health_key("*", "loopclosure", "*"), self._on_listener)

    def _on_listener(self, sample) -> None:   # a Zenoh thread
        key = str(sample.key_expr)
        if topics.parse_health_key(key)[0] == self.robot:
            return
        if sample.kind == zenoh.SampleKind.DELETE:
            self.listeners.discard(key)
        else:
            self.listeners.add(key)

    def close(self) -> None:
        if self.journal is not None:
            self.journal.close()
        self.recognition.keyframes.close()

    # --- this robot's frames ----------------------------------------------------------------------
    def own_place(self, place: int, frame: int) -> None:
        self.own[place] = frame

    def on_frame(self, header, frame: int, observed, camera_bytes: int) -> dict:
        """After the detector saw a frame: publish a new place, match the frame against the
        other robots' places (and an earlier frame against the places that arrived since),
        publish what it confirms; the votes, for the frame's journal record."""
        self.counters["camera_bytes"] += camera_bytes
        match = observed.match
        if match.is_new:
            self.own_place(match.template_id, frame)
            keyframe = self.service.detector.keyframes.get(match.template_id)
            if keyframe is not None:
                self._send_places(header, [PlaceRecord(place=match.template_id, frame=frame, keyframe=keyframe.to_bytes())])
        view = observed.view
        seen = self.recognition.observe(frame, view.features, view.camera)
        if seen.confirmed:
            self._send_closures(header, seen.confirmed)
        self.maybe_sync()
        record = {}
        if seen.votes:
            record["fleet"] = [vote_record(vote) for vote in seen.votes]
        if seen.late:
            record["fleet_late"] = [[late_frame, [vote_record(vote) for vote in votes]] for late_frame, votes in seen.late]
        return record

    def replay(self, frame: int, record: dict) -> None:
        if record.get("new"):
            self.own_place(record["template"], frame)
        self.recognition.replay(frame, tuple(vote_of(v) for v in record.get("fleet", ())),
                                tuple((int(late_frame), tuple(vote_of(v) for v in votes))
                                      for late_frame, votes in record.get("fleet_late", ())))

    def _send_places(self, header, places: list[PlaceRecord]) -> None:
        message = FleetPlaces(header=header.model_copy(update={"robot": self.robot}), places=places,
                              place_count=len(self.own))
        self.service.publish("fleet/place", message)
        if not self.listeners:   # Zenoh sends a sample to no one when nothing matches it
            self.counters["fleet_places_unheard"] += len(places)
            return
        self.counters["fleet_places_sent"] += len(places)
        self.counters["fleet_bytes_sent"] += len(codec.encode(message))

    def _send_closures(self, header, confirmed: tuple[FleetConfirmed, ...]) -> None:
        self.counters["fleet_closures"] += len(confirmed)
        for closure in confirmed:
            m = closure.measurement
            log.info("inter-robot closure %d confirmed: frame %d ↔ robot %s frame %d (place %d), %d votes, "
                     "measurement %s%s", closure.index, closure.frame, closure.robot, closure.matched_frame,
                     closure.place, closure.votes, m.method, f" ({m.error})" if m.error else "")
        self.service.publish("fleet/closure", FleetClosures(header=header.model_copy(update={"robot": self.robot}), closures=[closure_record(c) for c in confirmed],
                                                            closure_count=len(self.recognition.confirmed)))

    # --- other robots' places ---------------------------------------------------------------------
    def on_place(self, message: FleetPlaces) -> None:
        robot = message.header.robot
        if robot == self.robot:
            return
        self.counters["fleet_bytes_received"] += sum(len(p.keyframe) for p in message.places)
        for record in message.places:
            self._learn(robot, record)
        if self.recognition.next_missing(robot) < message.place_count:
            self.next_sync = 0.0   # a gap: ask for what is missing at once

    def _learn(self, robot: str, record: PlaceRecord) -> None:
        if record.place in self.recognition.known(robot):
            return
        try:
            keyframe = Keyframe.from_bytes(record.keyframe)
        except KeyframeError as error:
            self.counters["fleet_places_refused"] += 1
            log.warning("loopclosure: place %d of robot %s refused: %s", record.place, robot, error)
            return
        with self.lock:
            self.recognition.add(robot, record.place, record.frame, keyframe)
        if self.journal is not None:   # after its keyframe: a crash between leaves a keyframe the restart drops
            self.journal.append({"robot": robot, "place": record.place, "frame": record.frame})
        self.counters["fleet_places_learnt"] += 1

    def maybe_sync(self) -> None:
        now = time.monotonic()
        if now < self.next_sync:
            return
        self.next_sync = now + self.sync.sync_period
        session = self.service.session
        robots = set()
        for reply in session.liveliness().get(topics.health_key("*", "loopclosure", "*"), timeout=1.0):
            if reply.ok is not None:
                robots.add(topics.parse_health_key(str(reply.ok.key_expr))[0])
        for robot in sorted(robots - {self.robot}):
            self._fetch(robot)

    def _fetch(self, robot: str) -> None:
        """Ask ``robot`` for the places this one lacks, batch after batch."""
        while True:
            start = self.recognition.next_missing(robot)
            got = None
            for reply in self.service.session.get(f"{topics.key(robot, 'fleet/places')}?from={start}",
                                                  timeout=QUERY_TIMEOUT_S):
                if reply.ok is None:
                    continue
                try:
                    got = codec.decode(reply.ok.payload.to_bytes(), FleetPlaces, str(reply.ok.encoding))
                except codec.CodecError as error:
                    log.warning("loopclosure: places of robot %s: %s", robot, error)
            if got is None or not got.places:
                return
            self.counters["fleet_bytes_received"] += sum(len(p.keyframe) for p in got.places)
            for record in got.places:
                self._learn(robot, record)
            if len(got.places) < REPLY_PLACES:
                return

    # --- queryables (Zenoh threads) ---------------------------------------------------------------
    def places_reply(self, parameter) -> FleetPlaces:
        start = parse_from(parameter("from"))
        with self.lock:
            places = []
            for place in range(start, start + REPLY_PLACES):
                frame = self.own.get(place)
                keyframe = self.service.detector.keyframes.get(place) if frame is not None else None
                if keyframe is None:
                    break
                places.append(PlaceRecord(place=place, frame=frame, keyframe=keyframe.to_bytes()))
            count = len(self.own)
        message = FleetPlaces(header=self.service.header(self.service.last_seq, 0.0), places=places, place_count=count)
        if places:
            self.counters["fleet_places_resent"] += len(places)
            self.counters["fleet_bytes_sent"] += len(codec.encode(message))
        return message

    def closures_reply(self, parameter) -> FleetClosures:
        start = parse_from(parameter("from"))
        confirmed = self.recognition.confirmed
        chosen = confirmed[start:start + REPLY_CLOSURES]
        return FleetClosures(header=self.service.header(self.service.last_seq, 0.0),
                             closures=[closure_record(c) for c in chosen], closure_count=len(confirmed))

    def extra_counters(self) -> dict[str, float]:
        return {**self.counters, "fleet_places_known": len(self.recognition)}


def closure_record(closure: FleetConfirmed) -> FleetClosureRecord:
    m = closure.measurement
    measured = m.method != "none"
    return FleetClosureRecord(index=closure.index, frame=closure.frame, matched_robot=closure.robot,
                              matched_place=closure.place, matched_frame=closure.matched_frame, votes=closure.votes,
                              measurement=m.method,
                              relative_pose=PlanarIncrement(forward=m.forward, left=m.left, yaw=m.yaw) if measured else None,
                              covariance=list(m.covariance) if measured else None, inliers=m.inliers,
                              geometry_error=m.error)
