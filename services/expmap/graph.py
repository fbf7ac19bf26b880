"""The experience map (Milford & Wyeth 2008/2010), a pure core: numbers in, numbers out.

Per frame it takes the path integrator's pose in its odometry frame (x, y, heading), the
frame's view template id, and a confirmed loop closure when there is one:

- The robot is always "at" a current experience, at an offset (in that experience's frame)
  given by the odometry travelled since it was last there.
- A new experience is made when that offset exceeds `new_experience_distance` or the view
  template changes; it is linked from the current one by the offset (an odometric link).
- A confirmed loop closure links the current experience to the experience made at the matched
  frame. What the link asserts depends on `closure`:
  - `metric` (default): the relative pose the images measured between the matched frame and
    the current one, with its uncertainty (services/loopclosure/geometry.py). The robot stays
    at its own experience; the closure is a measurement the optimiser weighs.
  - `ratslam`: the paper's snap-to-experience: the robot *is* at the matched experience (the
    link carries the odometric offset), and that experience becomes current.
- The optimiser (`optimizer`) places the experiences:
  - `gtsam` (default): a pose graph solved incrementally by iSAM2 (optimizers.PoseGraph), with
    odometric links weighted by the distance they span and closure links under a robust kernel.
    After solving, a closure whose residual is still beyond `closure_gate` standard deviations
    is refused: the odometry contradicts it. Its link stays in the map as evidence
    (`accepted=False`) but is taken out of the graph, so it does not bend the map.
  - `ratslam`: RatSLAM's graph relaxation (optimizers.Relaxation); every closure is accepted.

A frame's cost does not grow with the map under `gtsam`: experiences are found by dictionaries,
links are appended, the solver holds only the experiences closures join (optimizers.PoseGraph)
and its update touches what a closure affects, and the published poses are refreshed for what
the solver re-eliminated plus a fixed number of others per solve (optimizers.REFRESH_PER_SOLVE),
so every experience is refreshed within a bounded number of solves. `final_poses()` gives every
experience's best estimate (for exports).

Everything is deterministic: the same inputs in the same order give the same map, which is
what lets a restarted service rebuild its map by replaying the log of its inputs. `rebase()`
is part of those inputs: it returns the map's whole state as arrays (`state()`) and rebuilds the
optimiser from it (gtsam: a fresh iSAM2 given every factor, at the current estimate), so a map
restored from that state (`ExperienceMap.restore`) goes on exactly, bit for bit, as the rebased
one. iSAM2's incremental state itself cannot be saved, and a fresh solve differs from it by up
to about a centimetre; rebasing the live map at the same point makes the restored map the same
map (services/expmap/store.py writes such checkpoints).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from services.common.geometry import adjoint, between, compose, inverse
from services.common.settings import check, setting
from services.common.stages import CLOSURES, MAP_OPTIMIZERS
from services.expmap.links import ClosureInput, Link
from services.expmap.localizer import Localizer
from services.expmap.optimizers import PoseGraph, Relaxation

OPTIMIZERS = MAP_OPTIMIZERS
KERNELS = ("cauchy", "geman_mcclure", "dcs", "huber", "none")
FATES = ("accepted", "rejected", "unmeasured", "unmatched")   # what becomes of a confirmed closure


@dataclass(frozen=True)
class MapParams:
    """The experience map's settings (table `[expmap]`, env `GRIDSLAM_EXPMAP_*`, presets: the
    expmap service's config model is derived from these declarations)."""

    LABEL = "experience map"

    new_experience_distance: float = setting(1.0, gt=0, help="Metres of odometry before a new experience.")
    optimizer: str = setting("gtsam", choices=OPTIMIZERS,
                             help="gtsam: a pose graph solved by iSAM2; ratslam: RatSLAM's graph relaxation.")
    closure: str = setting("metric", choices=CLOSURES,
                           help="metric: a closure carries the relative pose measured from the images; ratslam: the "
                                "robot snaps to the matched experience (the paper's model).")
    # RatSLAM relaxation (optimizer = ratslam)
    correction: float = setting(0.5, gt=0, le=1, help="Relaxation correction factor (RatSLAM: 0.5; optimizer ratslam).")
    relax_passes: int = setting(10, ge=0, help="Relaxation passes on a frame with a loop closure (optimizer ratslam).")
    relax_every_frame: int = setting(1, ge=0, help="Relaxation passes on every other frame (optimizer ratslam).")
    # Pose graph (optimizer = gtsam). The odometry's uncertainty comes with it (each frame's
    # increment covariance, from the ego-motion estimator through the integrator); for a frame
    # without one, its standard deviations are modelled from the frame's motion:
    odometry_translation_sigma: float = setting(
        0.05, ge=0, help="A frame's odometry without a covariance: translation std dev per metre moved.")
    odometry_heading_sigma: float = setting(
        0.01, ge=0, help="A frame's odometry without a covariance: heading std dev per metre moved, rad.")
    odometry_turn_sigma: float = setting(
        0.05, ge=0, help="A frame's odometry without a covariance: heading std dev per radian turned.")
    odometry_translation_floor: float = setting(0.005, gt=0, help="Added to every odometric link's translation std dev, m.")
    odometry_heading_floor: float = setting(0.001, gt=0, help="Added to every odometric link's heading std dev, rad.")
    # Closures: a snapped closure (closure = ratslam) asserts the robot is at the experience, within these
    snap_translation_sigma: float = setting(0.5, gt=0, help="closure ratslam: std dev of 'the robot is at the experience', m.")
    snap_heading_sigma: float = setting(0.2, gt=0, help="closure ratslam: heading std dev of the snap, rad.")
    mono_scale_sigma: float = setting(0.5, gt=0, help="A monocular closure's length: std dev as a fraction of the odometry's.")
    robust_kernel: str = setting("cauchy", choices=KERNELS, help="Robust kernel on closure factors (optimizer gtsam).")
    kernel_width: float = setting(1.0, gt=0, help="The kernel's constant, in standard deviations of the closure.")
    closure_gate: float = setting(
        3.0, gt=0, help="Refuse a closure whose innovation exceeds this many standard deviations (optimizer gtsam).")
    closure_iterations: int = setting(4, ge=0, help="Extra solver iterations on a frame with an accepted closure.")
    # Sessions: closures joining two parts of the map (a later session to the saved map) must agree
    join_closures: int = setting(3, ge=1, help="Closures of one frame that must agree on where a part of the map is "
                                               "before it is joined to another (a later session to the saved map).")
    join_gate: float = setting(3.0, gt=0, help="Standard deviations within which those closures must agree.")

    def check(self) -> None:
        check(self)


@dataclass
class FrameResult:
    """What one frame did to the map."""

    frame: int
    experience: int
    pose: tuple[float, float, float]          # the robot's map pose
    offset: tuple[float, float, float] | None = None   # the pose in its experience's frame (None: localising, no experience of its own)
    new_experiences: list[int] = field(default_factory=list)
    new_links: list[Link] = field(default_factory=list)
    moved: list[int] = field(default_factory=list)   # experiences moved by the optimiser beyond 1 mm / 0.1 mrad
    closure: str | None = None                # this frame's closure: accepted, rejected, unmeasured, unmatched
    residual: float | None = None             # the closure's residual after solving, standard deviations
    decisions: list[tuple[ClosureInput, str, float | None]] = field(default_factory=list)   # every closure decided
    localized: bool = True                    # the pose is in the map's frame (not: a part not joined to it yet,
                                              # or a localisation not placed yet: the pose is its odometry's)
    joined: list[int] = field(default_factory=list)   # parts joined to the map's frame at this frame
    placed: bool = False                      # a localisation was placed (again) at this frame
    lost: bool = False                        # a localisation was lost at this frame


@dataclass(frozen=True, eq=False)
class MapState:
    """A consistent copy of the map's published state (for snapshots)."""

    frame: int | None
    poses: np.ndarray
    templates: list[int]
    created: list[int]
    links: list[Link]


IDENTITY = (0.0, 0.0, 0.0)
# Frames whose offset covariance is kept, for closures of earlier frames of a confirmed run (the
# consistency rule's window is ten frames).
RECENT_COVARIANCES = 64
JOINED_PRIOR_SIGMA = 1e3   # the prior a joined part keeps (m, rad): it only keeps the solve determinate
JOIN_WINDOW = 10           # frames whose closures between two parts are weighed together (the rule's window)


class ExperienceMap:
    def __init__(self, params: MapParams = MapParams()):
        params.check()
        self.params = params
        self._poses = np.zeros((64, 3))                 # published experience poses (x, y, heading), first len(self) rows
        self.templates: list[int] = []
        self.created: list[int] = []                    # frame of creation
        self.links: list[Link] = []
        self.current: int | None = None
        self.anchor: tuple[float, float, float] | None = None   # odometry pose when last at `current`
        self.last_odometry: tuple[float, float, float] | None = None
        self.offset_covariance = np.zeros((3, 3))       # of the offset from `current` (right-hand tangent)
        self.frames: list[tuple[int, int, tuple[float, float, float]]] = []   # (frame, experience, offset)
        self.last_frame: int | None = None
        self.closures = dict.fromkeys(FATES, 0)
        self.decisions: list[tuple[int, int, str]] = []   # (frame, matched frame, what became of its closure)
        self.residuals: list[float | None] = []         # each decision's closure residual, standard deviations
        self._frame_at: dict[int, int] = {}             # frame → its row of `frames`
        self._by_template: dict[int, int] = {}          # template → its latest experience
        self._recent_covariances: dict[int, np.ndarray] = {}   # frame → its offset covariance, the last frames'
        self.parts: list[int] = []                      # the part of the graph each experience is in (0: the map's frame)
        self.anchors: dict[int, int] = {0: 0}           # each part → its first experience
        self._new_part = False                          # the next frame starts a part (a new session)
        self._joining: list[tuple] = []                 # recent placements of a part in another's frame (_join)
        self.localizer = None                           # a localisation session on this map (localizer.py)
        self.optimizer = PoseGraph(self) if params.optimizer == "gtsam" else Relaxation(self)

    def __len__(self) -> int:
        return len(self.templates)

    @property
    def poses(self) -> np.ndarray:
        """The published experience poses (E, 3), as of the last frame (a view, not a copy)."""
        return self._poses[:len(self.templates)]

    def step(self, frame: int, odometry: tuple[float, float, float], template_id: int,
             closure: ClosureInput | None = None, covariance: tuple[float, ...] | None = None,
             earlier: tuple[ClosureInput, ...] = ()) -> FrameResult:
        """Apply one frame: odometry pose (x, y, heading), its view template, an optional
        confirmed closure, the covariance (3×3 row-major, forward, left, yaw) of the
        odometry's increment since the previous frame, when the odometry knows it, and the
        closures of earlier frames confirmed with this frame's (`ClosureInput.frame`: frames
        the map has, at most RECENT_COVARIANCES back)."""
        if not all(math.isfinite(v) for v in odometry):
            raise ValueError(f"frame {frame}: odometry pose {odometry} is not finite")
        if self.localizer is not None:
            return self._localize(frame, odometry, closure, covariance, earlier)
        result = FrameResult(frame, -1, (0.0, 0.0, 0.0))
        if self.current is None or self._new_part:
            # The map starts as the odometry frame; a later session as a part of its own, where its
            # odometry puts it, until closures join it to the map.
            new = self._add_experience(odometry, template_id, frame, result, anchor=self.current is not None)
            self._move_to(new, odometry)
            self._new_part = False
        else:
            self._accumulate(between(self.last_odometry, odometry), covariance)
        self.last_odometry = odometry
        offset = between(self.anchor, odometry)
        target, matched_offset = self._place_of(closure) if closure is not None else (None, None)
        if closure is not None and target is None:
            result.closure = "unmatched"
        if target is not None and target != self.current and self.params.closure == "ratslam":
            # The robot is where the matched frame was: it moves to that experience (RatSLAM; a
            # match of the experience it is at already moves nothing, as a metric closure to it).
            link = self._closure_link(self.current, target, offset, IDENTITY, matched_offset, frame)
            if self._decide(link, self._snap_covariance(), result):
                self._move_to(target, compose(odometry, inverse(matched_offset)))
                offset = matched_offset
        if math.hypot(offset[0], offset[1]) > self.params.new_experience_distance or \
                template_id != self.templates[self.current]:
            new = self._add_experience(compose(tuple(self._poses[self.current]), offset), template_id, frame, result)
            link = Link(self.current, new, *offset, frame)
            self.optimizer.add_link(link, self._link_covariance())
            self._add_link(link, result)
            self._move_to(new, odometry)
            offset = (0.0, 0.0, 0.0)
        across: list[tuple] = []   # closures to another part: decided together (_join)
        if target is not None and self.params.closure == "metric":
            if not closure.measured:
                result.closure = "unmeasured"
            elif self.parts[target] != self.parts[self.current]:
                across.append((closure, self.current, offset, self.offset_covariance.copy(), target, matched_offset, frame))
            elif target != self.current:
                measurement, covariance = self._measurement(closure, target, matched_offset, offset, self.current,
                                                            self.offset_covariance)
                self._decide(self._closure_link(self.current, target, offset, measurement, matched_offset, frame),
                             covariance, result)
        if result.closure is not None:
            self._record(frame, closure, result)
        self._recent_covariances[frame] = self.offset_covariance.copy()
        self._recent_covariances.pop(frame - RECENT_COVARIANCES, None)
        for closure in earlier:
            self._earlier_closure(closure, frame, result, across)
        if across:
            self._join(across, result)
        moved = self.optimizer.solve(closure_frame=any(fate in ("accepted", "rejected") for _, fate, _ in result.decisions))
        result.moved = [i for i in moved if i not in result.new_experiences]
        result.experience = self.current
        result.pose, result.offset = compose(tuple(self._poses[self.current]), offset), offset
        result.localized = self.parts[self.current] == 0
        self._frame_at[frame] = len(self.frames)
        self.frames.append((frame, self.current, offset))
        self.last_frame = frame
        return result

    def _record(self, frame: int, closure: ClosureInput, result: FrameResult) -> None:
        self.closures[result.closure] += 1
        self.decisions.append((frame, closure.matched_frame, result.closure))
        self.residuals.append(result.residual)
        result.decisions.append((closure, result.closure, result.residual))

    def _earlier_closure(self, closure: ClosureInput, frame: int, result: FrameResult, across: list) -> None:
        """A closure of an earlier frame (metric closures only: a snap moves the robot, which an
        earlier frame cannot), linked from the experience the robot was at then; "unmatched" when
        that frame is not among the map's last RECENT_COVARIANCES."""
        row = self._frame_at.get(closure.frame)
        covariance = self._recent_covariances.get(closure.frame)
        decided = FrameResult(closure.frame, -1, IDENTITY)
        target = None
        if row is not None and covariance is not None and closure.frame < frame:
            _, source, offset = self.frames[row]
            target, matched_offset = self._place_of(closure)
        if target is None:
            decided.closure = "unmatched"
        elif self.params.closure != "metric":
            return
        elif not closure.measured:
            decided.closure = "unmeasured"
        elif self.parts[target] != self.parts[source]:
            across.append((closure, source, offset, covariance, target, matched_offset, closure.frame))
            return
        elif target != source:
            measurement, link_covariance = self._measurement(closure, target, matched_offset, offset, source, covariance)
            self._decide(self._closure_link(source, target, offset, measurement, matched_offset, closure.frame),
                         link_covariance, decided)
        if decided.closure is not None:
            self._record(closure.frame, closure, decided)
            result.decisions += decided.decisions
            result.new_links += decided.new_links

    def _join(self, across: list, result: FrameResult) -> None:
        """Closures between two parts of the graph: each says where its frame's part is in the
        other part's frame. When `join_closures` of those of the last JOIN_WINDOW frames agree
        (within `join_gate` standard deviations), the younger part is moved there (its prior
        made weak) and this frame's closures are tested and kept as any other; until then they
        are refused, kept as evidence. A closure to a place with a look-alike (an experience of a
        closure the map refused) joins nothing."""
        frame = result.frame
        self._joining = [entry for entry in self._joining if entry[0] > frame - JOIN_WINDOW]
        aliased = self.aliased()
        placements = []
        for closure, source, offset, covariance, target, matched_offset, link_frame in across:
            measurement, link_covariance = self._measurement(closure, target, matched_offset, offset, source, covariance)
            link = self._closure_link(source, target, offset, measurement, matched_offset, link_frame)
            placements.append((closure, link, link_covariance))
            if {source, target} & aliased:
                continue
            # Where the source experience is in the target's part, and so the transform of its part.
            implied = compose(tuple(self._poses[target]), inverse(link.transform))
            moved_part, fixed_part = sorted((self.parts[source], self.parts[target]), reverse=True)
            transform = compose(implied, inverse(tuple(self._poses[source])))
            if moved_part != self.parts[source]:   # the target's part is the younger: move it the other way
                transform = inverse(transform)
            self._joining.append((frame, transform, link_covariance, moved_part, fixed_part))
        best: list[int] = []
        for _, transform_i, covariance_i, moved_i, fixed_i in self._joining:
            agreeing = [j for j, (_, transform_j, covariance_j, moved_j, fixed_j) in enumerate(self._joining)
                        if (moved_j, fixed_j) == (moved_i, fixed_i)
                        and _mahalanobis(transform_i, transform_j, covariance_i + covariance_j) <= self.params.join_gate]
            if len(agreeing) > len(best):
                best = agreeing
        if len(best) >= self.params.join_closures:
            _, transform, _, moved_part, fixed_part = self._joining[best[0]]
            self._move_part(moved_part, fixed_part, transform)
            self._joining = [entry for entry in self._joining if moved_part not in entry[3:5]]
            result.joined.append(moved_part)
        for closure, link, covariance in placements:
            decided = FrameResult(link.frame, -1, IDENTITY)
            if self.parts[link.source] == self.parts[link.target]:
                # Composed anew: the moved part's poses changed, not the measurement.
                self._decide(link, covariance, decided)
            else:
                self.optimizer.add_refused(covariance)
                self._add_link(dataclasses.replace(link, accepted=False), decided)
                decided.closure = "rejected"
            self._record(link.frame, closure, decided)
            result.decisions += decided.decisions
            result.new_links += decided.new_links

    def _move_part(self, part: int, into: int, transform: tuple[float, float, float]) -> None:
        """Move every experience of ``part`` by ``transform`` into the frame of part ``into``,
        which it joins: the graph is rebuilt at the moved poses, the part's prior made weak."""
        members = np.flatnonzero(np.array(self.parts) == part)
        state = self.state()
        for index in members.tolist():
            state["poses"][index] = compose(transform, tuple(state["poses"][index]))
        # The optimiser's own state moves with them, the part's prior weak: the closures hold it now.
        self.optimizer.move_part(state, members, self.anchors[part], transform, JOINED_PRIOR_SIGMA)
        for index in members.tolist():
            self._poses[index] = state["poses"][index]
            self.parts[index] = into
        del self.anchors[part]
        self.optimizer.rebuild(state)

    def aliased(self) -> set[int]:
        """The experiences that have a look-alike: those of the closures the map refused."""
        return {e for link in self.links if link.loop_closure and not link.accepted for e in (link.source, link.target)}

    def start_session(self, localize: bool = False) -> None:
        """The frames from here on are a later session on this map: its own part of the graph until
        closures join it, or (``localize``) a localisation that adds nothing to the map."""
        if localize:
            self.localizer = Localizer(self.final_poses(), {f: (e, o) for f, e, o in self.frames}, aliased=self.aliased())
        else:
            self._new_part = True

    def _localize(self, frame, odometry, closure, covariance, earlier) -> FrameResult:
        own = (dataclasses.replace(closure, frame=frame),) if closure is not None else ()
        located = self.localizer.step(frame, odometry, own + tuple(earlier), covariance)
        result = FrameResult(frame, self.localizer.experience, located.pose, localized=located.localized,
                             placed=located.placed, lost=located.lost)
        for decided, fate, residual in located.decisions:
            self.closures[fate] += 1
            self.decisions.append((decided.frame, decided.matched_frame, fate))
            self.residuals.append(residual)
            result.decisions.append((decided, fate, residual))
        self.last_frame = frame
        return result

    def trajectory(self) -> list[tuple[int, float, float, float]]:
        """(frame, x, y, heading) of every frame, placed on the final map (`final_poses`)."""
        poses = self.final_poses()
        return [(frame, *compose(tuple(poses[experience]), offset)) for frame, experience, offset in self.frames]

    def place(self, keys: np.ndarray, poses: np.ndarray) -> None:
        """The optimiser's estimates `poses` (K, 3) of the experiences `keys` become their
        published poses (optimizers.PlacedMap)."""
        self._poses[keys] = poses

    def final_poses(self) -> np.ndarray:
        """Every experience's best estimate (E, 3); costs a pass over the map (for exports, not per frame)."""
        return self.optimizer.estimate()

    def snapshot(self) -> MapState:
        """A copy of the published state; the caller serialises it outside its lock."""
        count = len(self.templates)
        return MapState(self.last_frame, self._poses[:count].copy(), self.templates[:count], self.created[:count],
                        self.links[:])

    # --- checkpoints ------------------------------------------------------------------------------
    def state(self) -> dict[str, np.ndarray]:
        """The map's whole state as arrays (copies), the optimiser's included: what `restore` takes."""
        if self.current is None:
            raise ValueError("an empty map has no state to save")
        links = self.links
        return {"poses": self.poses.copy(), "templates": np.array(self.templates, dtype=np.int64),
                "created": np.array(self.created, dtype=np.int64),
                "links": np.array([(k.source, k.target, k.frame, k.loop_closure, k.accepted) for k in links],
                                  dtype=np.int64).reshape(-1, 5),
                "link_transforms": np.array([k.transform for k in links], dtype=float).reshape(-1, 3),
                "frames": np.array([(frame, experience) for frame, experience, _ in self.frames], dtype=np.int64).reshape(-1, 2),
                "frame_offsets": np.array([offset for _, _, offset in self.frames], dtype=float).reshape(-1, 3),
                "current": np.array([self.current, self.last_frame], dtype=np.int64),
                "odometry": np.array([self.anchor, self.last_odometry], dtype=float),
                "offset_covariance": self.offset_covariance.copy(),
                "closure_counts": np.array([self.closures[fate] for fate in FATES], dtype=np.int64),
                "decisions": np.array([(frame, matched, FATES.index(fate)) for frame, matched, fate in self.decisions],
                                      dtype=np.int64).reshape(-1, 3),
                "residuals": np.array([np.nan if r is None else r for r in self.residuals], dtype=float),
                "recent_covariances": np.array([(frame, *c.ravel()) for frame, c in self._recent_covariances.items()],
                                               dtype=float).reshape(-1, 10),
                "parts": np.array(self.parts, dtype=np.int64),
                "anchors": np.array(sorted(self.anchors.items()), dtype=np.int64).reshape(-1, 2),
                "new_part": np.array(self._new_part),
                "joining": np.array([(f, *t, *c.ravel(), moved, fixed) for f, t, c, moved, fixed in self._joining],
                                    dtype=float).reshape(-1, 15),
                **self.optimizer.state()}

    @classmethod
    def restore(cls, params: MapParams, state: dict[str, np.ndarray]) -> ExperienceMap:
        """The map a `state()` describes, its optimiser rebuilt as `rebase` rebuilds it (KeyError,
        ValueError or IndexError when `state` is no map state)."""
        experience_map = cls(params)
        experience_map._load(state)
        experience_map.optimizer.rebuild(state)
        return experience_map

    def rebase(self) -> dict[str, np.ndarray]:
        """Rebuild the optimiser from the map's state and return that state: from here on this map
        and `restore(params, state)` are the same map."""
        state = self.state()
        self.optimizer.rebuild(state)
        return state

    def _load(self, state: dict[str, np.ndarray]) -> None:
        poses = np.asarray(state["poses"], dtype=float)
        self._poses = np.zeros((max(64, 2 * len(poses)), 3))
        self._poses[:len(poses)] = poses
        self.templates = [int(v) for v in state["templates"]]
        self.created = [int(v) for v in state["created"]]
        if not len(poses) == len(self.templates) == len(self.created):
            raise ValueError("experience arrays of different lengths")
        self.links = [Link(int(s), int(t), *(float(v) for v in transform), int(frame), bool(closure), bool(accepted))
                      for (s, t, frame, closure, accepted), transform in zip(state["links"], state["link_transforms"],
                                                                             strict=True)]
        self.frames = [(int(frame), int(experience), tuple(float(v) for v in offset))
                       for (frame, experience), offset in zip(state["frames"], state["frame_offsets"], strict=True)]
        self.current, self.last_frame = (int(v) for v in state["current"])
        anchor, last = state["odometry"]
        self.anchor, self.last_odometry = tuple(float(v) for v in anchor), tuple(float(v) for v in last)
        self.offset_covariance = np.array(state["offset_covariance"], dtype=float).reshape(3, 3)
        self.closures = {fate: int(count) for fate, count in zip(FATES, state["closure_counts"], strict=True)}
        self.decisions = [(int(frame), int(matched), FATES[fate]) for frame, matched, fate in state["decisions"]]
        self.residuals = [None if np.isnan(r) else float(r) for r in state["residuals"]]
        self._recent_covariances = {int(row[0]): np.array(row[1:]).reshape(3, 3)
                                    for row in state.get("recent_covariances", np.zeros((0, 10)))}
        self.parts = [int(v) for v in state["parts"]] if "parts" in state else [0] * len(self.templates)
        self.anchors = {int(p): int(e) for p, e in state["anchors"]} if "anchors" in state else {0: 0}
        self._new_part = bool(state["new_part"]) if "new_part" in state else False
        self._joining = [(int(row[0]), tuple(row[1:4]), np.array(row[4:13]).reshape(3, 3), int(row[13]), int(row[14]))
                         for row in state.get("joining", np.zeros((0, 15)))]
        if len(self.parts) != len(self.templates):
            raise ValueError("experience parts of another map size")
        if len(self.residuals) != len(self.decisions):
            raise ValueError("decisions and residuals of different lengths")
        self._frame_at = {frame: row for row, (frame, _, _) in enumerate(self.frames)}
        self._by_template = {template: index for index, template in enumerate(self.templates)}

    # --- closures ---------------------------------------------------------------------------------
    def _place_of(self, closure: ClosureInput) -> tuple[int | None, tuple[float, float, float] | None]:
        """Where the matched frame was: the experience the robot was at then and its offset from
        it; a frame the map never had falls back to the latest experience of the matched template."""
        index = self._frame_at.get(closure.matched_frame)
        if index is not None:
            _, experience, offset = self.frames[index]
            return experience, offset
        experience = self._by_template.get(closure.matched_template)
        return (experience, IDENTITY) if experience is not None else (None, None)

    @staticmethod
    def _closure_link(current: int, target: int, offset, measurement, matched_offset, frame: int) -> Link:
        """The link current → target when the current frame, at `offset` from `current`, sits at
        `measurement` from the matched frame, at `matched_offset` from `target`:
        offset ∘ measurement⁻¹ ∘ matched_offset⁻¹."""
        transform = compose(compose(offset, inverse(measurement)), inverse(matched_offset))
        return Link(current, target, *transform, frame, loop_closure=True)

    def _decide(self, link: Link, covariance: np.ndarray, result: FrameResult) -> bool:
        accepted, residual = self.optimizer.add_closure(link, covariance)
        self._add_link(dataclasses.replace(link, accepted=accepted), result)
        result.closure = "accepted" if accepted else "rejected"
        result.residual = residual
        return accepted

    def _measurement(self, closure: ClosureInput, target: int, matched_offset, offset, source: int,
                     offset_covariance: np.ndarray) -> tuple[tuple[float, float, float], np.ndarray]:
        """The measured pose of the revisiting frame (at `offset` from experience `source`, its
        covariance `offset_covariance`) in the matched frame's, and the covariance of the link
        source → target that carries it (right-hand tangent perturbation, the convention of the
        pose graph's factors)."""
        covariance = np.array(closure.covariance, dtype=float).reshape(3, 3)
        forward, left = closure.forward, closure.left
        if closure.method == "mono":   # a direction: its length from the map's own estimate
            frame_pose = compose(tuple(self._poses[source]), offset)
            matched_pose = compose(tuple(self._poses[target]), matched_offset)
            length = math.hypot(*between(matched_pose, frame_pose)[:2])
            norm = math.hypot(forward, left) or 1.0
            forward, left = forward / norm * length, left / norm * length
            along = np.array([forward, left]) / max(length, 1e-9)
            covariance = covariance.copy()
            covariance[:2, :2] = covariance[:2, :2] * length ** 2 + \
                np.outer(along, along) * (self.params.mono_scale_sigma * length) ** 2
        measurement = (forward, left, closure.yaw)
        # Component noise of the measurement → right tangent: rotate the translation part into its frame.
        c, s = math.cos(closure.yaw), math.sin(closure.yaw)
        to_tangent = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        # The odometry from the source experience to the frame (the offset) is uncertain too.
        tangent = to_tangent @ covariance @ to_tangent.T + offset_covariance
        # The link offset ∘ measurement⁻¹ ∘ matched⁻¹, with measurement ∘ Exp(δ) (or offset ∘ Exp(δ)), is the
        # link ∘ Exp(∓Ad(matched ∘ measurement) δ).
        carry = adjoint(compose(matched_offset, measurement))
        return measurement, carry @ tangent @ carry.T

    def _snap_covariance(self) -> np.ndarray:
        p = self.params
        return np.diag([p.snap_translation_sigma ** 2, p.snap_translation_sigma ** 2, p.snap_heading_sigma ** 2])

    def _accumulate(self, increment, covariance) -> None:
        """Carry the offset's covariance across one frame's increment and add the increment's:
        (offset ∘ Exp(ε)) ∘ increment = (offset ∘ increment) ∘ Exp(Ad(increment⁻¹) ε)."""
        if covariance is None:   # modelled from the frame's own motion
            p = self.params
            distance = math.hypot(increment[0], increment[1])
            translation = p.odometry_translation_sigma * distance
            heading = p.odometry_heading_sigma * distance + p.odometry_turn_sigma * abs(increment[2])
            covariance = np.diag([translation ** 2, translation ** 2, heading ** 2])
        else:
            covariance = np.asarray(covariance, dtype=float).reshape(3, 3)
        carry = adjoint(inverse(increment))
        self.offset_covariance = carry @ self.offset_covariance @ carry.T + covariance

    def _link_covariance(self) -> np.ndarray:
        """An odometric link's covariance: the offset's, with the floors added."""
        p = self.params
        floor = np.diag([p.odometry_translation_floor ** 2, p.odometry_translation_floor ** 2, p.odometry_heading_floor ** 2])
        return self.offset_covariance + floor

    def _move_to(self, experience: int, odometry) -> None:
        self.current, self.anchor = experience, odometry
        self.offset_covariance = np.zeros((3, 3))

    # --- growth -----------------------------------------------------------------------------------
    def _add_experience(self, pose, template_id: int, frame: int, result: FrameResult, anchor: bool = False) -> int:
        """A new experience; ``anchor``: the first of a new part of the graph."""
        index = len(self.templates)
        if index == len(self._poses):   # grow geometrically: amortised O(1) per experience
            self._poses = np.concatenate([self._poses, np.zeros_like(self._poses)])
        self._poses[index] = pose
        self.templates.append(template_id)
        self.created.append(frame)
        self._by_template[template_id] = index
        if anchor:
            part = max(self.anchors) + 1
            self.anchors[part] = index
        self.parts.append(part if anchor else (self.parts[self.current] if self.current is not None else 0))
        self.optimizer.add_experience(index, pose, anchor)
        result.new_experiences.append(index)
        return index

    def _add_link(self, link: Link, result: FrameResult) -> None:
        self.links.append(link)
        result.new_links.append(link)


def _mahalanobis(a, b, covariance: np.ndarray) -> float:
    """Mahalanobis distance between two planar poses (their difference in a's frame)."""
    difference = np.array(between(a, b))
    return float(math.sqrt(max(difference @ np.linalg.solve(covariance, difference), 0.0)))
