"""The loop-closure detector, a pure core: place recognition, the paper's consistency rule, and the
geometry of a confirmed closure, frame by frame. The loopclosure service and the offline map
build (services/offline/mapping.py) drive the same object.

Per frame: the view is recognised (`place_recognition`, one of PLACE_RECOGNITIONS):

- `scanline`: RatSLAM's view templates (templates.py), the paper's model;
- `bow`: a bag of binary words (bow.py): the frame's ORB features quantised into visual words,
  the stored places that share most of them verified geometrically;
- `sequence`: SeqSLAM's sequences of small patch-normalised images (sequence.py).

A view unlike every stored place becomes a new place, and its frame a keyframe (geometry.py:
features, and for stereo their depth; kept in a KeyframeStore, or in memory). A match of a place
stored at least `recent_frames` ago is a *vote*, a possible closure; each vote is measured as it
is made (`geometry`), so that a closure confirmed later by the rule (consistency.py) carries the
measurement of its own frame — the rule confirms the run of votes, earlier frames included:

- `auto` (default): from the images — stereo PnP against the matched keyframe's 3D points when
  that frame was stereo, the essential matrix (rotation and direction) when it was monocular
  with a calibration — and from the view templates (`scanline`) without a calibration;
- `scanline`: RatSLAM's view-template model: the robot is at the matched place (within
  `scanline_translation_sigma`), turned by the templates' relative angle (within
  `scanline_heading_sigma`);
- `none`: no measurement (the map can then only snap, closure = ratslam).

A closure whose geometry fails is published with measurement `none` and the reason, and counted.
Everything a frame changes is in its Observation (`journal_view`, `vote`), so that `replay`
rebuilds the same state from a journal after a restart.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

import numpy as np

from services.common.errors import ConfigError
from services.loopclosure.consistency import ConsistencyParams, ConsistencyRule, Vote
from services.loopclosure.geometry import ClosureGeometry, Features, GeometryParams, Keyframe
from services.loopclosure.places import PLACE_RECOGNITIONS, Recognised, recogniser
from services.loopclosure.templates import ViewMatch
from services.common.frames import Camera

GEOMETRIES = ("auto", "scanline", "none")
MEMORY_KEYFRAMES = 4096   # keyframes kept without a store (the oldest go first)


@dataclass(frozen=True)
class Measurement:
    """A closure's relative pose: the current frame in the matched frame's body frame, and its
    covariance (forward, left, yaw), or why there is none (method "none", `error`)."""

    method: str
    forward: float = 0.0
    left: float = 0.0
    yaw: float = 0.0
    covariance: tuple[float, ...] = ()
    inliers: int = 0
    error: str = ""


@dataclass(frozen=True)
class MeasuredVote:
    """A possible closure of a frame and its measurement."""

    template: int
    matched_frame: int
    measurement: Measurement


@dataclass(frozen=True)
class Confirmed:
    """A loop closure the rule confirmed: ``frame`` (this frame, or an earlier one of the run)
    revisits the place stored at ``matched_frame``."""

    frame: int
    matched_frame: int
    matched_template: int
    votes: int
    measurement: Measurement


@dataclass(frozen=True)
class Observation:
    match: ViewMatch
    closures: tuple[Confirmed, ...]             # confirmed at this frame, oldest frame first
    vote: MeasuredVote | None = None            # this frame's possible closure
    journal_view: dict | None = None            # what the recogniser must replay (a new place, a sequence patch)
    candidate: tuple[int, float] | None = None  # the best older place's frame and score (precision–recall)
    view: _Frame | None = None                  # the frame as the detector saw it (its features, found once)


class MemoryKeyframes:
    """Keyframes in memory when no store file is given, the newest `limit` of them."""

    def __init__(self, limit: int = MEMORY_KEYFRAMES):
        self._keyframes: collections.OrderedDict[int, Keyframe] = collections.OrderedDict()
        self.limit = limit

    def append(self, template_id: int, keyframe: Keyframe) -> bool:
        self._keyframes[template_id] = keyframe
        while len(self._keyframes) > self.limit:
            self._keyframes.popitem(last=False)
        return True

    def get(self, template_id: int) -> Keyframe | None:
        return self._keyframes.get(template_id)

    def truncate(self, count: int) -> int:
        stale = [t for t in self._keyframes if t >= count]
        for template_id in stale:
            del self._keyframes[template_id]
        return len(stale)

    def close(self) -> None:
        pass


@dataclass
class _Frame:
    """The current frame as the detector sees it: its images and, once found, its features."""

    seq: int
    left: np.ndarray
    right: np.ndarray | None
    camera: Camera | None
    geometry: ClosureGeometry
    _features: Features | None = field(default=None, repr=False)

    @property
    def features(self) -> Features:
        if self._features is None:
            self._features = self.geometry.features(self.left)
        return self._features


class LoopClosureDetector:
    def __init__(self, places, consistency: ConsistencyParams, geometry: GeometryParams = GeometryParams(),
                 mode: str = "auto", scanline_translation_sigma: float = 0.5, scanline_heading_sigma: float = 0.05,
                 keyframes=None, place_recognition: str = "scanline"):
        """``places``: the recogniser's parameters (TemplateParams for scanline, BowParams for
        bow, SequenceParams for sequence: places.py)."""
        if mode not in GEOMETRIES:
            raise ConfigError(f"loop closure: geometry {mode!r} is not one of {', '.join(GEOMETRIES)}")
        if place_recognition not in PLACE_RECOGNITIONS:
            raise ConfigError(f"loop closure: place recognition {place_recognition!r} is not one of "
                              f"{', '.join(PLACE_RECOGNITIONS)}")
        self.rule = ConsistencyRule(consistency)
        self.geometry = ClosureGeometry(geometry)
        self.places = recogniser(place_recognition, places, consistency.recent_frames)
        self.place_recognition = place_recognition
        self.mode = mode
        self.scanline_covariance = tuple(np.diag([scanline_translation_sigma ** 2, scanline_translation_sigma ** 2,
                                                  scanline_heading_sigma ** 2]).ravel())
        self.keyframes = keyframes if keyframes is not None else MemoryKeyframes()
        # The measured votes of the rule's window, by frame: a run confirmed later takes its
        # earlier frames' measurements from here.
        self._measured: dict[int, Measurement] = {}
        self.counts = {"closures": 0, "geometry_failed": 0}
        self.session = 0
        self.localize = False   # a localisation session: no place is stored

    def start_session(self, session: int, localize: bool = False) -> None:
        """The frames from here on are session ``session`` of the map (their numbers count from
        services.common.layout.session_base(session)): votes do not run across sessions, and a
        localisation stores no place."""
        self.rule = ConsistencyRule(self.rule.params)
        self._measured.clear()
        self.places.start_session()
        self.session, self.localize = session, localize

    def observe(self, seq: int, left: np.ndarray, right: np.ndarray | None = None,
                camera: Camera | None = None) -> Observation:
        """Recognise one frame (grey or BGR images; `right` for stereo), keep its keyframe when it
        is a new place, measure its possible closures, and return the closures the rule confirms."""
        frame = _Frame(seq, left, right, camera, self.geometry)
        recognised: Recognised = self.places.observe(seq, frame, self.keyframes.get, learn=not self.localize)
        match, journal_view = recognised.match, recognised.journal_view
        if match.is_new:
            keyframe = None
            if self.mode == "auto" or self.places.needs_keyframes:
                keyframe = self.geometry.keyframe(left, right, camera)
                self.keyframes.append(match.template_id, keyframe)
            journal_view = {**(journal_view or {}), **(self.places.store(match, keyframe) or {})}
        chosen = self.rule.choose(seq, recognised.votes)
        vote = None if chosen is None else MeasuredVote(*chosen, self._measure(*chosen, match, frame))
        return Observation(match, self._confirm(seq, vote), vote, journal_view, recognised.candidate, frame)

    def replay(self, seq: int, match: ViewMatch, journal_view: dict | None, vote: MeasuredVote | None) \
            -> tuple[Confirmed, ...]:
        """Rebuild the state one journaled frame left (its place, if new, its vote, its counts);
        the keyframes are in the store already."""
        self.places.replay(seq, match, journal_view)
        return self._confirm(seq, vote)

    def _confirm(self, seq: int, vote: MeasuredVote | None) -> tuple[Confirmed, ...]:
        for frame in [frame for frame in self._measured if frame <= seq - self.rule.params.window]:
            del self._measured[frame]
        if vote is None:
            self.rule.update(seq, -1, True, seq)
            return ()
        self._measured[seq] = vote.measurement
        closure = self.rule.update(seq, vote.template, False, vote.matched_frame)
        if closure is None:
            return ()
        run = [*closure.earlier, Vote(seq, closure.matched_frame, closure.matched_template)]
        confirmed = tuple(Confirmed(v.frame, v.matched_frame, v.template, closure.votes, self._measured[v.frame])
                          for v in run)
        self.counts["closures"] += len(confirmed)
        self.counts["geometry_failed"] += sum(c.measurement.method == "none" and self.mode != "none" for c in confirmed)
        return confirmed

    def _measure(self, template: int, matched_frame: int, match: ViewMatch, frame: _Frame) -> Measurement:
        if self.mode == "none":
            return Measurement("none", error="geometry off")
        keyframe = self.keyframes.get(template) if self.mode == "auto" else None
        if keyframe is not None and (frame.camera or keyframe.camera) is not None:
            pose = self.geometry.relative_pose(keyframe, frame.left, frame.camera, frame.features)
            if not pose.ok:
                return Measurement("none", inliers=pose.inliers, error=pose.reason)
            return Measurement(pose.method, pose.forward, pose.left, pose.yaw,
                               tuple(float(v) for v in pose.covariance.ravel()), pose.inliers)
        if self.mode == "auto" and keyframe is None and frame.camera is not None:
            return Measurement("none", error=f"no keyframe of template {template}")
        # RatSLAM's model: at the matched place, turned by the views' relative angle.
        angle = match.relative_angle if match.template_id == template else 0.0
        return Measurement("scanline", 0.0, 0.0, angle, self.scanline_covariance)

    def close(self) -> None:
        self.keyframes.close()
