"""Localisation on a saved map, a pure core: where the robot is in the saved map's frame, from its
odometry and the loop closures against the map's experiences (which it never changes).

The robot starts *not localised*: its pose is its odometry's, in the odometry frame. A closure
says where one of its frames was relative to a frame of the saved map; with the map's pose of
that frame (an experience's pose composed with the frame's offset from it) it gives the map pose
of the robot's frame, and the odometry since then the pose now. Because places look alike, one
closure places nothing: the robot is placed when closures agree — at least `min_consistent` of
those of the last `window` frames (a run the consistency rule confirmed comes as one batch)
within `consistency_gate` standard deviations of each other, the largest such set — and placed
where they put it. A closure to a place the map knows has a look-alike (an experience of a
closure the map refused when it was made) places nothing: the robot is placed once it sees a
place that has none. From then on the odometry moves the estimate and its uncertainty grows with
the increments' covariances (SE(2) adjoints, as the map's links do); every further closure is
tested against it (Mahalanobis distance of its innovation within `closure_gate`, the map's own
test) and, when it passes, fused (an extended Kalman update on the right-hand tangent). Closures
it refuses that agree among themselves as consistently as a placement must move it there
(relocalised). With no accepted closure for `lost_distance` metres of travel the robot is
*lost*: it says so, and is placed again only as at the start.

A monocular closure measures the direction, not the length, of the translation between the two
views: it is tested and fused only once the robot is placed, its length taken from the
estimate (as the map does).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import numpy as np

from services.common.settings import check, setting
from services.common.geometry import adjoint, between, compose, inverse, wrap
from services.expmap.graph import ClosureInput

RECENT_ODOMETRY = 64   # frames whose odometry pose is kept (a confirmed run's frames are within ten)


@dataclass(frozen=True)
class LocalizerParams:
    LABEL = "localisation"

    min_consistent: int = setting(3, ge=1, help="Closures of one batch that must agree before the robot is placed.")
    consistency_gate: float = setting(3.0, gt=0, help="Standard deviations within which two closures' placements agree.")
    closure_gate: float = setting(3.0, gt=0, help="Largest innovation of a closure fused once placed, standard deviations.")
    lost_distance: float = setting(30.0, gt=0, help="Metres travelled without an accepted closure before the robot is lost.")
    window: int = setting(10, ge=1, help="Frames whose closures are weighed together to place the robot.")
    odometry_translation_sigma: float = setting(0.05, ge=0, help="A frame's odometry without a covariance: "
                                                                  "translation std dev per metre moved.")
    odometry_heading_sigma: float = setting(0.01, ge=0, help="The same, heading std dev per metre moved, rad.")
    odometry_turn_sigma: float = setting(0.05, ge=0, help="The same, heading std dev per radian turned.")

    def check(self) -> None:
        check(self)


@dataclass
class LocalizedPose:
    frame: int
    localized: bool
    pose: tuple[float, float, float]            # map frame when localised, else the odometry's
    decisions: list[tuple[ClosureInput, str, float | None]] = field(default_factory=list)
    placed: bool = False                        # placed (again) at this frame
    lost: bool = False                          # lost at this frame


class Localizer:
    """Feed every frame in order (`step`); the saved map's experience poses and frames never change."""

    def __init__(self, experience_poses: np.ndarray, frames: dict[int, tuple[int, tuple[float, float, float]]],
                 params: LocalizerParams = LocalizerParams(), aliased: set[int] = frozenset()):
        """``experience_poses`` (E, 3) of the saved map; ``frames``: its frames → (experience,
        offset); ``aliased``: its experiences that have a look-alike."""
        params.check()
        self.params = params
        self.experience_poses = np.asarray(experience_poses, dtype=float)
        self.map_frames = frames
        self.aliased = set(aliased)
        # Closures of the last frames not (yet) used, with the map pose they gave their frame.
        self._candidates: collections.deque[tuple[int, ClosureInput, tuple, np.ndarray]] = collections.deque()
        self.experience = 0                                   # the map experience of the last accepted closure
        self.localized = False
        self.pose: tuple[float, float, float] | None = None   # map pose when localised
        self.covariance = np.zeros((3, 3))
        self.last_odometry: tuple[float, float, float] | None = None
        self.since_fix = 0.0                                  # metres since the last accepted closure
        self.odometry: collections.OrderedDict[int, tuple[float, float, float]] = collections.OrderedDict()
        self.counts = {"placed": 0, "lost": 0, "accepted": 0, "rejected": 0, "unmatched": 0, "unmeasured": 0}

    def step(self, frame: int, odometry: tuple[float, float, float], closures: tuple[ClosureInput, ...] = (),
             covariance: tuple[float, ...] | None = None) -> LocalizedPose:
        if not all(math.isfinite(v) for v in odometry):
            raise ValueError(f"frame {frame}: odometry pose {odometry} is not finite")
        result = LocalizedPose(frame, False, odometry)
        if self.last_odometry is not None and self.localized:
            increment = between(self.last_odometry, odometry)
            self.pose = compose(self.pose, increment)
            carry = adjoint(inverse(increment))
            self.covariance = carry @ self.covariance @ carry.T + self._increment_covariance(increment, covariance)
            self.since_fix += math.hypot(increment[0], increment[1])
        self.last_odometry = odometry
        self.odometry[frame] = odometry
        while len(self.odometry) > RECENT_ODOMETRY:
            self.odometry.popitem(last=False)
        while self._candidates and self._candidates[0][0] <= frame - self.params.window:
            self._candidates.popleft()
        if not self.localized:
            self._place(frame, closures, result)
        else:
            for closure in closures:
                self._fuse(frame, closure, result)
            if self._candidates:
                self._place(frame, (), result, again=True)
            if self.localized and self.since_fix > self.params.lost_distance:
                self.localized, self.pose = False, None
                self.counts["lost"] += 1
                result.lost = True
        result.localized = self.localized
        if self.localized:
            result.pose = self.pose
        return result

    # --- placing and fusing -----------------------------------------------------------------------
    def _implied(self, frame: int, closure: ClosureInput, length: float | None = None):
        """(map pose of the current frame, its 3×3 covariance) that a closure implies, or the
        reason it implies none."""
        place = self.map_frames.get(closure.matched_frame)
        revisiting = closure.frame if closure.frame >= 0 else frame
        if place is None or revisiting not in self.odometry:
            return "unmatched"
        if not closure.measured:
            return "unmeasured"
        experience, offset = place
        matched = compose(tuple(self.experience_poses[experience]), offset)
        forward, left = closure.forward, closure.left
        covariance = np.array(closure.covariance, dtype=float).reshape(3, 3)
        if closure.method == "mono":
            if length is None:
                return "unmeasured"
            norm = math.hypot(forward, left) or 1.0
            forward, left = forward / norm * length, left / norm * length
            along = np.array([forward, left]) / max(length, 1e-9)
            covariance = covariance.copy()
            covariance[:2, :2] = covariance[:2, :2] * length ** 2 + np.outer(along, along) * (0.5 * length) ** 2
        at_frame = compose(matched, (forward, left, closure.yaw))
        since = between(self.odometry[revisiting], self.odometry[frame])
        c, s = math.cos(closure.yaw), math.sin(closure.yaw)
        to_tangent = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        carry = adjoint(inverse(since))
        return compose(at_frame, since), carry @ (to_tangent @ covariance @ to_tangent.T) @ carry.T

    def _place(self, frame: int, closures: tuple[ClosureInput, ...], result: LocalizedPose, again: bool = False) -> None:
        """Place the robot where the most closures of the window agree, when they are enough
        (``again``: it is placed, and they contradict where: relocalised)."""
        for closure in closures:
            outcome = self._implied(frame, closure)
            if isinstance(outcome, str):
                self._decide(result, closure, outcome, None)
            elif self.map_frames[closure.matched_frame][0] in self.aliased:
                self._decide(result, closure, "rejected", None)   # a place with a look-alike places nothing
            else:
                revisiting = closure.frame if closure.frame >= 0 else frame
                pose, covariance = outcome
                self._candidates.append((revisiting, closure, compose(pose, between(self.odometry[frame],
                                                                                    self.odometry[revisiting])), covariance))
        # Each candidate's placement of the current frame.
        now = [(closure, compose(at, between(self.odometry[seen], self.odometry[frame])), covariance)
               for seen, closure, at, covariance in self._candidates]
        best: list[int] = []
        for _, pose_i, covariance_i in now:
            agreeing = [j for j, (_, pose_j, covariance_j) in enumerate(now)
                        if _distance(pose_i, pose_j, covariance_i + covariance_j) <= self.params.consistency_gate]
            if len(agreeing) > len(best):
                best = agreeing
        if len(best) < self.params.min_consistent:
            for closure in closures:
                if not any(decided is closure for decided, _, _ in result.decisions):
                    self._decide(result, closure, "rejected", None)
            return
        # Placed: the agreeing closures fused in turn (the first as the start).
        chosen = [now[j] for j in best]
        self.pose, self.covariance = chosen[0][1], chosen[0][2]
        self.localized, self.since_fix = True, 0.0
        self.counts["placed"] += 1
        result.placed = True
        self._candidates.clear()
        self.experience = self.map_frames[chosen[0][0].matched_frame][0]
        used = {id(closure) for closure, _, _ in chosen}
        for _, pose, covariance in chosen[1:]:
            self._update(pose, covariance)
        for closure in closures:
            if not any(decided is closure for decided, _, _ in result.decisions):
                self._decide(result, closure, "accepted" if id(closure) in used else "rejected", None)

    def _fuse(self, frame: int, closure: ClosureInput, result: LocalizedPose) -> None:
        length = None
        place = self.map_frames.get(closure.matched_frame)
        if place is not None:
            experience, offset = place
            matched = compose(tuple(self.experience_poses[experience]), offset)
            length = math.hypot(*between(matched, self.pose)[:2])
        outcome = self._implied(frame, closure, length)
        if isinstance(outcome, str):
            self._decide(result, closure, outcome, None)
            return
        measured, noise = outcome
        residual = _distance(self.pose, measured, self.covariance + noise)
        if residual > self.params.closure_gate:
            self._decide(result, closure, "rejected", residual)
            if self.map_frames[closure.matched_frame][0] not in self.aliased:   # evidence of being elsewhere
                revisiting = closure.frame if closure.frame >= 0 else frame
                self._candidates.append((revisiting, closure, compose(measured, between(self.odometry[frame],
                                                                                        self.odometry[revisiting])), noise))
            return
        self._update(measured, noise)
        self.experience = place[0]
        self._decide(result, closure, "accepted", residual)

    def _update(self, measured, noise: np.ndarray) -> None:
        """The extended Kalman update of the estimate with a measured map pose of the current frame."""
        innovation = np.array(between(self.pose, measured))        # right-hand tangent, approximately
        innovation[2] = float(wrap(innovation[2]))
        gain = self.covariance @ np.linalg.inv(self.covariance + noise)
        self.pose = compose(self.pose, tuple(gain @ innovation))
        self.covariance = (np.eye(3) - gain) @ self.covariance
        self.since_fix = 0.0

    def _decide(self, result: LocalizedPose, closure: ClosureInput, fate: str, residual: float | None) -> None:
        self.counts[fate] += 1
        result.decisions.append((closure, fate, residual))

    def _increment_covariance(self, increment, covariance) -> np.ndarray:
        if covariance is not None:
            return np.asarray(covariance, dtype=float).reshape(3, 3)
        p = self.params
        distance = math.hypot(increment[0], increment[1])
        translation = p.odometry_translation_sigma * distance
        heading = p.odometry_heading_sigma * distance + p.odometry_turn_sigma * abs(increment[2])
        return np.diag([translation ** 2, translation ** 2, heading ** 2])


def _distance(a, b, covariance: np.ndarray) -> float:
    """Mahalanobis distance between two planar poses (their difference in a's frame)."""
    difference = np.array(between(a, b))
    difference[2] = float(wrap(difference[2]))
    return float(math.sqrt(max(difference @ np.linalg.solve(covariance, difference), 0.0)))
