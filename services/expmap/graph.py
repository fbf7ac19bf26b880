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

from services.common.errors import ConfigError

OPTIMIZERS = ("gtsam", "ratslam")
CLOSURES = ("metric", "ratslam")
KERNELS = ("cauchy", "geman_mcclure", "dcs", "huber", "none")
METHODS = ("stereo", "mono", "scanline")
FATES = ("accepted", "rejected", "unmeasured", "unmatched")   # what becomes of a confirmed closure


@dataclass(frozen=True)
class MapParams:
    new_experience_distance: float = 1.0   # metres of odometry before a new experience
    optimizer: str = "gtsam"               # gtsam (pose graph, iSAM2) or ratslam (relaxation)
    closure: str = "metric"                # metric (measured relative pose) or ratslam (snap to the experience)
    # RatSLAM relaxation (optimizer = ratslam)
    correction: float = 0.5                # RatSLAM's correction factor
    relax_passes: int = 10                 # relaxation passes per frame after a loop closure
    relax_every_frame: int = 1             # passes on frames without a loop closure
    # Pose graph (optimizer = gtsam). The odometry's uncertainty comes with it (each frame's
    # increment covariance, from the ego-motion estimator through the integrator); for a frame
    # without one, its standard deviations are modelled from the frame's motion:
    odometry_translation_sigma: float = 0.05   # metres per metre travelled in the frame
    odometry_heading_sigma: float = 0.01       # radians per metre travelled in the frame
    odometry_turn_sigma: float = 0.05          # radians per radian turned in the frame
    odometry_translation_floor: float = 0.005  # metres added to every link's standard deviation
    odometry_heading_floor: float = 0.001      # radians added to every link's standard deviation
    # Closures: a snapped closure (closure = ratslam) asserts the robot is at the experience, within these
    snap_translation_sigma: float = 0.5    # metres
    snap_heading_sigma: float = 0.2        # radians
    mono_scale_sigma: float = 0.5          # a monocular closure's translation length: this fraction of the odometry's
    robust_kernel: str = "cauchy"          # on closure links: cauchy, geman_mcclure, dcs, huber or none
    kernel_width: float = 1.0              # the kernel's constant, in standard deviations of the closure
    closure_gate: float = 3.0              # refuse a closure whose residual after solving exceeds this (std devs)
    closure_iterations: int = 4            # extra solver iterations on a frame with a closure

    def check(self) -> None:
        rules = (("new_experience_distance", self.new_experience_distance > 0), ("optimizer", self.optimizer in OPTIMIZERS),
                 ("closure", self.closure in CLOSURES), ("correction", 0 < self.correction <= 1),
                 ("relax_passes", self.relax_passes >= 0), ("relax_every_frame", self.relax_every_frame >= 0),
                 ("odometry_translation_sigma", self.odometry_translation_sigma >= 0),
                 ("odometry_heading_sigma", self.odometry_heading_sigma >= 0),
                 ("odometry_turn_sigma", self.odometry_turn_sigma >= 0),
                 ("odometry_translation_floor", self.odometry_translation_floor > 0),
                 ("odometry_heading_floor", self.odometry_heading_floor > 0),
                 ("snap_translation_sigma", self.snap_translation_sigma > 0), ("snap_heading_sigma", self.snap_heading_sigma > 0),
                 ("mono_scale_sigma", self.mono_scale_sigma > 0), ("robust_kernel", self.robust_kernel in KERNELS),
                 ("kernel_width", self.kernel_width > 0), ("closure_gate", self.closure_gate > 0),
                 ("closure_iterations", self.closure_iterations >= 0))
        for name, ok in rules:
            if not ok:
                raise ConfigError(f"experience map: invalid {name} = {getattr(self, name)!r}")


# --- planar poses (x, y, heading) ---------------------------------------------------------------
def wrap(angle):
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def compose(pose: tuple[float, float, float], offset: tuple[float, float, float]) -> tuple[float, float, float]:
    """pose ∘ offset for planar poses (x, y, heading)."""
    x, y, th = pose
    dx, dy, dth = offset
    c, s = math.cos(th), math.sin(th)
    return x + c * dx - s * dy, y + s * dx + c * dy, float(wrap(th + dth))


def between(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    """The offset of b in a's frame: a ∘ between(a, b) = b."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    c, s = math.cos(a[2]), math.sin(a[2])
    return c * dx + s * dy, -s * dx + c * dy, float(wrap(b[2] - a[2]))


def inverse(pose: tuple[float, float, float]) -> tuple[float, float, float]:
    return between(pose, (0.0, 0.0, 0.0))


def adjoint(pose: tuple[float, float, float]) -> np.ndarray:
    """SE(2) adjoint: carries a right-hand tangent perturbation across `pose`
    (pose ∘ Exp(ε) = Exp(Ad ε) ∘ pose); tangent order (x, y, heading)."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    return np.array([[c, -s, y], [s, c, -x], [0.0, 0.0, 1.0]])


# --- links and closures ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Link:
    """An edge: the pose of `target` in `source`'s frame (dx, dy, dheading)."""

    source: int
    target: int
    dx: float
    dy: float
    dheading: float
    frame: int
    loop_closure: bool = False
    accepted: bool = True       # False: a closure the map refused (kept as evidence, not optimised)

    @property
    def transform(self) -> tuple[float, float, float]:
        return self.dx, self.dy, self.dheading


@dataclass(frozen=True)
class ClosureInput:
    """A confirmed loop closure as the map takes it: the matched place, and (for metric
    closures) the pose of the current frame in the matched frame's body frame with its 3×3
    covariance (forward, left, yaw), row-major. `method` is how it was measured: stereo, mono
    (forward/left a unit direction: the length comes from the odometry) or scanline; an empty
    method means no measurement (its geometry failed): the map does not use it."""

    matched_template: int
    matched_frame: int
    method: str = ""
    forward: float = 0.0
    left: float = 0.0
    yaw: float = 0.0
    covariance: tuple[float, ...] = ()
    votes: int = 0                 # evidence only (loop_closures.csv): the consistency rule's votes,
    inliers: int = 0               # the feature matches behind the measurement,
    geometry_error: str = ""       # why there is no measurement
    frame: int = -1                # the revisiting frame when it is an earlier one than the step's (-1: the step's)

    @property
    def measured(self) -> bool:
        return self.method in METHODS and len(self.covariance) == 9


@dataclass
class FrameResult:
    """What one frame did to the map."""

    frame: int
    experience: int
    pose: tuple[float, float, float]          # the robot's map pose
    new_experiences: list[int] = field(default_factory=list)
    new_links: list[Link] = field(default_factory=list)
    moved: list[int] = field(default_factory=list)   # experiences moved by the optimiser beyond 1 mm / 0.1 mrad
    closure: str | None = None                # this frame's closure: accepted, rejected, unmeasured, unmatched
    residual: float | None = None             # the closure's residual after solving, standard deviations
    decisions: list[tuple[ClosureInput, str, float | None]] = field(default_factory=list)   # every closure decided


@dataclass(frozen=True, eq=False)
class MapState:
    """A consistent copy of the map's published state (for snapshots)."""

    frame: int | None
    poses: np.ndarray
    templates: list[int]
    created: list[int]
    links: list[Link]


MOVED = np.array([1e-3, 1e-3, 1e-4])   # what counts as moved: 1 mm, 0.1 mrad
IDENTITY = (0.0, 0.0, 0.0)
# Frames whose offset covariance is kept, for closures of earlier frames of a confirmed run (the
# consistency rule's window is ten frames).
RECENT_COVARIANCES = 64


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
        from services.expmap.optimizers import PoseGraph, Relaxation   # they place this map's poses
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
        result = FrameResult(frame, -1, (0.0, 0.0, 0.0))
        if self.current is None:
            self._add_experience(odometry, template_id, frame, result)   # the map starts as the odometry frame
            self.current, self.anchor = 0, odometry
        else:
            self._accumulate(between(self.last_odometry, odometry), covariance)
        self.last_odometry = odometry
        offset = between(self.anchor, odometry)
        target, matched_offset = self._place_of(closure) if closure is not None else (None, None)
        if closure is not None and target is None:
            result.closure = "unmatched"
        if target is not None and self.params.closure == "ratslam":   # the robot is where the matched frame was
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
        if target is not None and self.params.closure == "metric":
            if not closure.measured:
                result.closure = "unmeasured"
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
            self._earlier_closure(closure, frame, result)
        moved = self.optimizer.solve(closure_frame=any(fate in ("accepted", "rejected") for _, fate, _ in result.decisions))
        result.moved = [i for i in moved if i not in result.new_experiences]
        result.experience = self.current
        result.pose = compose(tuple(self._poses[self.current]), offset)
        self._frame_at[frame] = len(self.frames)
        self.frames.append((frame, self.current, offset))
        self.last_frame = frame
        return result

    def _record(self, frame: int, closure: ClosureInput, result: FrameResult) -> None:
        self.closures[result.closure] += 1
        self.decisions.append((frame, closure.matched_frame, result.closure))
        self.residuals.append(result.residual)
        result.decisions.append((closure, result.closure, result.residual))

    def _earlier_closure(self, closure: ClosureInput, frame: int, result: FrameResult) -> None:
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
        elif target != source:
            measurement, link_covariance = self._measurement(closure, target, matched_offset, offset, source, covariance)
            self._decide(self._closure_link(source, target, offset, measurement, matched_offset, closure.frame),
                         link_covariance, decided)
        if decided.closure is not None:
            self._record(closure.frame, closure, decided)
            result.decisions += decided.decisions
            result.new_links += decided.new_links

    def trajectory(self) -> list[tuple[int, float, float, float]]:
        """(frame, x, y, heading) of every frame, placed on the final map (`final_poses`)."""
        poses = self.final_poses()
        return [(frame, *compose(tuple(poses[experience]), offset)) for frame, experience, offset in self.frames]

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
    def _add_experience(self, pose, template_id: int, frame: int, result: FrameResult) -> int:
        index = len(self.templates)
        if index == len(self._poses):   # grow geometrically: amortised O(1) per experience
            self._poses = np.concatenate([self._poses, np.zeros_like(self._poses)])
        self._poses[index] = pose
        self.templates.append(template_id)
        self.created.append(frame)
        self._by_template[template_id] = index
        self.optimizer.add_experience(index, pose)
        result.new_experiences.append(index)
        return index

    def _add_link(self, link: Link, result: FrameResult) -> None:
        self.links.append(link)
        result.new_links.append(link)
