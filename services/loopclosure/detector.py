"""The loop-closure detector, a pure core: view templates, the paper's consistency rule, and the
geometry of a confirmed closure, frame by frame. The loopclosure service and the offline map
build (services/expmap/evidence.py) drive the same object.

Per frame: the view is matched against the stored templates (templates.py); a view unlike any
becomes a new template, and its frame a keyframe (geometry.py: features, and for stereo their
depth; kept in a KeyframeStore, or in memory); the match is a vote of the consistency rule
(consistency.py). When the rule confirms a closure, its relative pose is measured
(`geometry`):

- `auto` (default): from the images — stereo PnP against the matched keyframe's 3D points when
  that frame was stereo, the essential matrix (rotation and direction) when it was monocular
  with a calibration — and from the view templates (`scanline`) without a calibration;
- `scanline`: RatSLAM's view-template model: the robot is at the matched place (within
  `scanline_translation_sigma`), turned by the templates' relative angle (within
  `scanline_heading_sigma`);
- `none`: no measurement (the map can then only snap, closure = ratslam).

A closure whose geometry fails is published with measurement `none` and the reason, and counted.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np

from services.common.errors import ConfigError
from services.loopclosure.consistency import Closure, ConsistencyParams, ConsistencyRule
from services.loopclosure.geometry import ClosureGeometry, GeometryParams, Keyframe
from services.loopclosure.templates import TemplateParams, ViewMatch, ViewTemplates
from services.source.frames import Camera

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
class Observation:
    match: ViewMatch
    closure: Closure | None
    measurement: Measurement | None   # for a closure


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


class LoopClosureDetector:
    def __init__(self, templates: TemplateParams, consistency: ConsistencyParams,
                 geometry: GeometryParams = GeometryParams(), mode: str = "auto",
                 scanline_translation_sigma: float = 0.5, scanline_heading_sigma: float = 0.05,
                 keyframes=None):
        if mode not in GEOMETRIES:
            raise ConfigError(f"loop closure: geometry {mode!r} is not one of {', '.join(GEOMETRIES)}")
        self.templates = ViewTemplates(templates)
        self.rule = ConsistencyRule(consistency)
        self.geometry = ClosureGeometry(geometry)
        self.mode = mode
        self.scanline_covariance = tuple(np.diag([scanline_translation_sigma ** 2, scanline_translation_sigma ** 2,
                                                  scanline_heading_sigma ** 2]).ravel())
        self.keyframes = keyframes if keyframes is not None else MemoryKeyframes()
        self.counts = {"closures": 0, "geometry_failed": 0}

    def observe(self, seq: int, left: np.ndarray, right: np.ndarray | None = None,
                camera: Camera | None = None) -> Observation:
        """Match one frame (grey or BGR images; `right` for stereo), keep its keyframe when it is a
        new template, and measure the closure the rule confirms."""
        match = self.templates.observe(left, seq)
        if match.is_new and self.mode == "auto":
            self.keyframes.append(match.template_id, self.geometry.keyframe(left, right, camera))
        closure = self.rule.update(seq, match.template_id, match.is_new, match.matched_frame)
        measurement = self._measure(match, closure, left, camera) if closure is not None else None
        return Observation(match, closure, measurement)

    def replay(self, seq: int, match: ViewMatch, patch: np.ndarray | None, measurement: Measurement | None) -> Closure | None:
        """Rebuild the state one journaled frame left (its template, if new, its vote, its counts);
        the keyframes are in the store already."""
        if match.is_new:
            self.templates.add(patch, seq)
        closure = self.rule.update(seq, match.template_id, match.is_new, match.matched_frame)
        if closure is not None:
            self.counts["closures"] += 1
            self.counts["geometry_failed"] += measurement is not None and measurement.method == "none" and \
                self.mode != "none"
        return closure

    def _measure(self, match: ViewMatch, closure: Closure, left, camera) -> Measurement:
        self.counts["closures"] += 1
        if self.mode == "none":
            return Measurement("none", error="geometry off")
        keyframe = self.keyframes.get(closure.matched_template) if self.mode == "auto" else None
        if keyframe is not None and (camera or keyframe.camera) is not None:
            pose = self.geometry.relative_pose(keyframe, left, camera)
            if not pose.ok:
                self.counts["geometry_failed"] += 1
                return Measurement("none", inliers=pose.inliers, error=pose.reason)
            return Measurement(pose.method, pose.forward, pose.left, pose.yaw,
                               tuple(float(v) for v in pose.covariance.ravel()), pose.inliers)
        if self.mode == "auto" and keyframe is None and camera is not None:
            self.counts["geometry_failed"] += 1
            return Measurement("none", error=f"no keyframe of template {closure.matched_template}")
        # RatSLAM's model: at the matched place, turned by the templates' relative angle.
        return Measurement("scanline", 0.0, 0.0, match.relative_angle, self.scanline_covariance)

    def close(self) -> None:
        self.keyframes.close()

