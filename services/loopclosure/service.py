"""loopclosure: RatSLAM view templates of every frame, the paper's loop-closure rule, and the
relative pose of each confirmed closure measured from the images (detector.py)."""

from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import threading
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, create_model, model_validator

from schemas import CameraFrame, LoopClosure, PlanarIncrement, ViewTemplate
from services.common.config import load_config
from services.common.convert import image_from_msg
from services.common.errors import ConfigError
from services.common.journal import SESSION, Journal, continue_session
from services.common.layout import MapReuseParams, add_map_reuse_arguments, map_files, session_base
from services.common.runtime import RuntimeConfig
from services.common.recovery import REPLAY_FRAMES
from services.common.service import Service
from services.common.settings import add_field_flag, config_fields, params_of
from services.common.stages import CLOSURES
from services.loopclosure.bow import BowParams
from services.loopclosure.consistency import ConsistencyParams
from services.loopclosure.detector import Confirmed, LoopClosureDetector, MeasuredVote, Measurement
from services.loopclosure.fleet import FleetParams
from services.loopclosure.fleet_member import FleetMember, FleetSyncParams
from services.loopclosure.geometry import GeometryParams
from services.loopclosure.keyframes import KeyframeStore, check_file as check_keyframes
from services.loopclosure.places import DEFAULT_PLACE_RECOGNITION, PLACE_RECOGNITIONS
from services.loopclosure.sequence import SequenceParams
from services.loopclosure.templates import TemplateParams, ViewMatch
from services.common.frames import Camera

log = logging.getLogger(__name__)


GEOMETRY_PREFIX = "geometry_"   # the closure geometry's keys (GeometryParams): geometry_features, geometry_ratio, ...
GEOMETRY_KEYS = tuple(field.name for field in dataclasses.fields(GeometryParams))


class _LoopClosureFields(BaseModel):
    """Configuration of the loopclosure service (table `[loopclosure]`, env `GRIDSLAM_LOOPCLOSURE_*`, presets)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    place_recognition: Literal[PLACE_RECOGNITIONS] = Field(
        DEFAULT_PLACE_RECOGNITION, description="How a frame's place is recognised: scanline (RatSLAM's view templates, the paper's model), "
                           "bow (a bag of binary words, verified geometrically) or sequence (SeqSLAM).")
    closure: Literal[CLOSURES] = Field(
        "metric", description="metric: measure each closure's relative pose; ratslam: no measurement (the map snaps).")
    geometry: Literal["auto", "scanline"] = Field(
        "auto", description="auto: the relative pose from the images (stereo PnP, or mono essential matrix); scanline: "
                            "RatSLAM's model, at the matched place turned by the templates' relative angle.")
    scanline_translation_sigma: float = Field(
        0.5, gt=0, description="scanline measurement: how far from the matched place the robot may be, m (std dev).")
    scanline_heading_sigma: float = Field(0.05, gt=0, description="scanline measurement: std dev of its relative angle, rad.")
    keyframe_store_mb: float = Field(512.0, gt=0, description="Largest size of the keyframe file beside the journal, MiB.")
    fleet: bool = Field(False, description="Take part in a fleet (docs/fleet.md): send this robot's new places to the other "
                                           "robots, learn theirs, and confirm inter-robot closures (keys fleet_*).")
    store: Path | None = Field(
        None, description="Journal of templates and matches, appended every frame; a restarted service resumes from it. "
                          "Keyframes go beside it (same name, suffix .keyframes).")

    def template_params(self) -> TemplateParams:
        return params_of(TemplateParams, self)

    def place_params(self):
        """The chosen place recogniser's parameters."""
        if self.place_recognition == "scanline":
            return self.template_params()
        params = params_of(BowParams, self, "bow_") if self.place_recognition == "bow" else \
            params_of(SequenceParams, self, "sequence_")
        params.check()
        return params

    def consistency_params(self) -> ConsistencyParams:
        return params_of(ConsistencyParams, self)

    @model_validator(mode="before")
    @classmethod
    def _geometry_table(cls, values: Any) -> Any:
        """The closure geometry's keys given as one table, `geometry_params = {features = 300}`
        (the older spelling of `geometry_features = 300`): still read, and noted."""
        if not isinstance(values, dict) or "geometry_params" not in values:
            return values
        values = dict(values)
        table = values.pop("geometry_params")
        if not isinstance(table, dict):
            raise ConfigError(f"[loopclosure] geometry_params must be a table, got {table!r}")
        unknown = sorted(set(table) - set(GEOMETRY_KEYS))
        if unknown:
            raise ConfigError(f"[loopclosure] geometry_params: unknown key(s) {', '.join(unknown)}; known: "
                              f"{', '.join(sorted(GEOMETRY_KEYS))}")
        if table:
            log.warning("[loopclosure] geometry_params is now spelled as single keys (%s); the old spelling still "
                        "works but will go", ", ".join(f"{GEOMETRY_PREFIX}{key}" for key in table))
        for key, value in table.items():
            values.setdefault(GEOMETRY_PREFIX + key, value)
        return values

    def geometry_parameters(self) -> GeometryParams:
        params = params_of(GeometryParams, self, GEOMETRY_PREFIX)
        params.check()
        return params

    def journal_params(self) -> dict[str, Any]:
        """The settings a journal is made with (its header), in the shape journals have always had
        them: the closure geometry's as the table `geometry_params` of the keys given."""
        geometry = {GEOMETRY_PREFIX + key for key in GEOMETRY_KEYS}
        # A journal made without a fleet keeps its header (and so --map of it) whatever the fleet keys are.
        params = self.model_dump(mode="json", exclude={"store", "keyframe_store_mb", "map", "localize", *geometry,
                                                       *([] if self.fleet else FLEET_KEYS)})
        given = self.model_dump(mode="json", include=geometry & self.model_fields_set)
        params["geometry_params"] = {key.removeprefix(GEOMETRY_PREFIX): value for key, value in given.items()}
        return params

    def detector(self, keyframes=None) -> LoopClosureDetector:
        mode = "none" if self.closure == "ratslam" else self.geometry
        return LoopClosureDetector(self.place_params(), self.consistency_params(), self.geometry_parameters(), mode,
                                   self.scanline_translation_sigma, self.scanline_heading_sigma, keyframes,
                                   self.place_recognition)


LoopClosureConfig = create_model("LoopClosureConfig", __base__=_LoopClosureFields, __doc__=_LoopClosureFields.__doc__,
                                 **config_fields(MapReuseParams),
                                 **config_fields(TemplateParams), **config_fields(ConsistencyParams),
                                 **config_fields(BowParams, "bow_"), **config_fields(SequenceParams, "sequence_"),
                                 **config_fields(GeometryParams, GEOMETRY_PREFIX),
                                 **config_fields(FleetParams, "fleet_"), **config_fields(FleetSyncParams, "fleet_"))
FLEET_KEYS = {"fleet", *(f"fleet_{f.name}" for cls in (FleetParams, FleetSyncParams) for f in dataclasses.fields(cls))}


def camera_of(message: CameraFrame, image: np.ndarray) -> Camera | None:
    info = message.camera_info
    if info is None:
        return None
    return Camera(fx=info.fx, fy=info.fy, cx=info.cx, cy=info.cy, baseline=info.baseline,
                  width=image.shape[1], height=image.shape[0])


JOURNAL_FORMAT = "gridslam-view-templates"
JOURNAL_VERSION = 3   # 3: place recognitions, votes measured as they are made


def _vote_record(vote: MeasuredVote | None) -> dict | None:
    return None if vote is None else dataclasses.asdict(vote)


def _measurement_of(record: dict) -> Measurement:
    return Measurement(**{**record, "covariance": tuple(record["covariance"])})


class LoopClosureService(Service):
    name = "loopclosure"
    exclusive = True   # the places and the closure votes run through every frame

    def __init__(self, runtime: RuntimeConfig, config: LoopClosureConfig, instance: str | None = None):
        super().__init__(runtime, instance)
        self.config = config
        keyframes = None
        if config.store is not None:
            keyframes = KeyframeStore(config.store.with_suffix(".keyframes"), int(config.keyframe_store_mb * 2**20))
        self.detector = config.detector(keyframes)
        # Frames already handled (from the journal after a restart), to answer a re-sent frame again.
        self.recent: collections.OrderedDict[int, tuple[ViewMatch, tuple[Confirmed, ...]]] = collections.OrderedDict()
        self.last_frame: int | None = None   # numbered across the map's sessions (services/common/layout.py)
        self.base = 0                        # the first frame number of this session
        self.journal = None
        self.lock = threading.RLock()   # the fleet's queryables read the keyframes a frame writes
        self.fleet = FleetMember(self, config) if config.fleet else None
        if config.store is not None:
            params = config.journal_params()
            vocabulary = getattr(self.detector.places, "vocabulary_id", None)
            header = {"format": JOURNAL_FORMAT, "version": JOURNAL_VERSION, "params": params,
                      **({"vocabulary": vocabulary} if vocabulary else {})}
            if config.map is not None and not (config.store.exists() and config.store.stat().st_size):
                start_session(config, header, keyframes)
            self.journal = Journal(config.store, header)
            for record in self.journal.records:
                self._replay(record)
            # A keyframe written just before a crash, whose frame the journal does not hold, is dropped.
            self.detector.keyframes.truncate(len(self.detector.places))
            if self.journal.records:
                log.info("loopclosure resumed from %s: %d frames, %d places", config.store,
                         len(self.journal.records), len(self.detector.places))

    def setup(self) -> None:
        self.subscribe("camera/frame", self.on_frame)
        if self.fleet is not None:
            self.fleet.setup()

    def on_idle(self) -> None:
        if self.fleet is not None:
            self.fleet.maybe_sync()

    def teardown(self) -> None:
        if self.journal is not None:
            self.journal.close()
        if self.fleet is not None:
            self.fleet.close()
        self.detector.close()

    def on_frame(self, message: CameraFrame) -> None:
        seq = message.header.seq
        frame = self.base + seq
        if self.last_frame is not None and frame <= self.last_frame:
            if frame in self.recent:   # handled before a restart: answer it again from the journal
                self._publish(message.header, *self.recent[frame])
            return
        left = image_from_msg(message.left)
        right = image_from_msg(message.right) if message.right is not None else None
        with self.lock:
            observed = self.detector.observe(frame, left, right, camera_of(message, left))
            fleet_record = {} if self.fleet is None else self.fleet.on_frame(
                message.header, frame, observed, len(message.left.data) + (len(message.right.data) if message.right else 0))
        for closure in observed.closures:
            m = closure.measurement
            log.info("loop closure confirmed at frame %d: frame %d ↔ frame %d (place %d), %d votes, measurement %s%s", seq,
                     closure.frame, closure.matched_frame, closure.matched_template, closure.votes, m.method,
                     f" ({m.error})" if m.error else "")
        self._publish(message.header, observed.match, observed.closures)
        # Journaled after publishing: a crash in between re-handles the frame, never loses it.
        if self.journal is not None:
            match = observed.match
            self.journal.append({"frame": frame, "template": match.template_id, "new": match.is_new,
                                 "distance": match.distance, "angle": match.relative_angle,
                                 "matched_frame": match.matched_frame, "shift": match.shift, "view": observed.journal_view,
                                 "vote": _vote_record(observed.vote), **fleet_record})
        self._remember(frame, observed.match, observed.closures)

    def _publish(self, header, match: ViewMatch, closures: tuple[Confirmed, ...]) -> None:
        for closure in closures:
            measurement = closure.measurement
            measured = measurement.method != "none"
            self.publish("loop/closure", LoopClosure(
                header=header, frame=closure.frame, matched_frame=closure.matched_frame,
                matched_template=closure.matched_template, votes=closure.votes, measurement=measurement.method,
                relative_pose=PlanarIncrement(forward=measurement.forward, left=measurement.left, yaw=measurement.yaw)
                if measured else None, covariance=list(measurement.covariance) if measured else None,
                inliers=measurement.inliers, geometry_error=measurement.error))
        self.publish("view/template", ViewTemplate(
            header=header, template_id=match.template_id, is_new=match.is_new, distance=match.distance,
            relative_angle=match.relative_angle, matched_frame=match.matched_frame,
            template_count=len(self.detector.places), loop_closure=bool(closures), loop_closures=len(closures)))

    def _replay(self, record: dict) -> None:
        """Rebuild the places and the consistency window from one journal record."""
        if SESSION in record:
            self.detector.start_session(record[SESSION], record["localize"])
            self.base = session_base(record[SESSION])
            log.info("loopclosure: session %d on the map of %s%s", record[SESSION], record["map"],
                     " (localisation)" if record["localize"] else "")
            return
        match = ViewMatch(record["template"], record["new"], record["distance"], record["angle"], record["matched_frame"],
                          record["shift"])
        vote = record["vote"]
        if vote is not None:
            vote = MeasuredVote(vote["template"], vote["matched_frame"], _measurement_of(vote["measurement"]))
        closures = self.detector.replay(record["frame"], match, record["view"], vote)
        if self.fleet is not None:
            self.fleet.replay(record["frame"], record)
        self._remember(record["frame"], match, closures)

    def _remember(self, frame: int, match: ViewMatch, closures: tuple[Confirmed, ...]) -> None:
        self.last_frame = frame
        self.recent[frame] = (match, closures)
        while len(self.recent) > REPLAY_FRAMES:
            self.recent.popitem(last=False)

    def extra_counters(self) -> dict[str, float]:
        counts = self.detector.counts
        return {**super().extra_counters(), "templates": len(self.detector.places), "loop_closures": counts["closures"],
                "closure_geometry_failed": counts["geometry_failed"],
                **(self.fleet.extra_counters() if self.fleet is not None else {})}


def start_session(config: LoopClosureConfig, header: dict, keyframes: KeyframeStore) -> None:
    """Begin the session's journal as the saved map's (checked, read only) and copy its keyframes."""
    files = map_files(config.map)
    check_keyframes(files["keyframes"])
    continue_session(files["places"], config.store, header, config.localize, config.map)
    keyframes.copy_from(files["keyframes"])


def add_place_recognition_argument(parser: argparse.ArgumentParser) -> None:
    """--place-recognition, shared by every command that runs the loop closure (run, demo, map build, the service)."""
    field = _LoopClosureFields.model_fields["place_recognition"]
    parser.add_argument("--place-recognition", choices=PLACE_RECOGNITIONS,
                        help=f"{field.description} (default {field.default})")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", help="view-template parameters for a dataset: synthetic, nubot, kitti, stlucia")
    add_field_flag(parser, LoopClosureConfig, "match_threshold", metavar="D")
    add_field_flag(parser, LoopClosureConfig, "store", metavar="FILE")
    add_field_flag(parser, LoopClosureConfig, "closure")
    add_place_recognition_argument(parser)
    add_map_reuse_arguments(parser)
    add_field_flag(parser, LoopClosureConfig, "fleet")


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    config = load_config(LoopClosureConfig, "loopclosure", preset=args.preset, config_file=args.config,
                         overrides={"match_threshold": args.match_threshold, "store": args.store, "closure": args.closure,
                                    "place_recognition": args.place_recognition, "map": args.map,
                                    "localize": args.localize, "fleet": args.fleet})
    config.geometry_parameters()   # a bad key fails at start, with one line
    config.place_params()
    if config.map is not None and config.store is None:
        raise ConfigError("[loopclosure] map: a session on a saved map needs a journal of its own (--store FILE)")
    if config.localize and config.map is None:
        raise ConfigError("[loopclosure] localize: localisation needs a saved map (--map DIR)")
    return LoopClosureService(runtime, config, args.instance).run()
