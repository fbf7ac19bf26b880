"""The fleet map (docs/fleet.md), a pure core: one pose graph over every robot's experiences.

Each robot's map comes in as its expmap builds it (`add_map`): its experiences, and its links
with their covariances — the odometric links as Gaussian factors, the closures its own map
accepted under the robust kernel (the ones it refused stay out, and mark their experiences as
having a look-alike). Each robot's map starts as a *part* of its own: its first experience held
by a firm prior where its own map put it, so until it is joined its experiences are in its own
map's frame. The fleet frame is the frame of the part of `frame_robot` (the first robot heard
of, when empty): robot a's map frame.

An inter-robot closure (`add_closure`) says where one robot's frame was relative to another's
place (the relative pose measured from the images by the revisiting robot's loop closure):

- between two parts not joined yet it is *pending*. The pending closures of the two parts are
  tested for pairwise consistency (consistency.py, Mangelson et al. 2018), and when a largest
  consistent set holds `join_closures` closures, spans `join_span` metres of both robots' maps
  (longer than any look-alike stretch: a look-alike's closures are consistent among themselves)
  and no rival set inconsistent with it holds as many, the parts are *joined*: the younger moves
  into the older's frame (the frame robot's stays), its priors made weak, the set's closures
  kept, and every other pending closure between them then tested as
  below. A closure with an end whose robot's own map knows a look-alike of it is refused at once;
- between parts already joined it is *tested* as the robot's own map tests a closure: added and
  solved, its innovation's Mahalanobis norm (νᵀΣ⁻¹r, optimizers.py) within `closure_gate`
  standard deviations accepts it (kept, as the join's closures, as a Gaussian factor: they are
  the parts' only links), beyond it refuses it (removed again);
- a joined pair of robots is *split* when later evidence contradicts it: when the closures
  between them that were refused hold a consistent set that would join them, more than twice
  as large as the set of accepted ones, every closure between the two goes back to pending (the accepted ones
  out of the graph) and the parts are decided again from all of them.

`joined_at` holds, per robot, the newest of its frames the join's closures name; `placed_at` its
newest frame the map had heard of when it was joined (its experiences' and its revisits' frames).

Everything is deterministic in the order of its inputs, so a journal of them (store.py) rebuilds
the same map; `state` / `restore` and `rebase` checkpoint it as the experience map does: the
solver is rebuilt from the Python-side factors at the current estimates, live and restored alike.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from services.common.geometry import adjoint, compose, inverse
from services.common.settings import check, setting
from services.fleetmap.consistency import Candidate, ConsistencyParams, consistency_graph, maximum_clique

PRIOR_SIGMA = 1e-6          # a part's own frame: its first experience where its robot's map put it
JOINED_PRIOR_SIGMA = 1e3    # ... once joined: it only keeps the solve determinate
LINEAR_TOLERANCE = 1e-6
SLOT = 1 << 32              # a key is slot · SLOT + experience
MOVED = np.array([1e-3, 1e-3, 1e-4])
FATES = ("pending", "accepted", "rejected", "unmeasured")


@dataclass(frozen=True)
class FleetParams:
    LABEL = "fleet map"

    frame_robot: str = setting("", help="The robot whose map frame is the fleet frame (empty: the first robot heard of).")
    join_closures: int = setting(3, ge=1, help="Mutually consistent inter-robot closures needed to join two robots' maps.")
    join_span: float = setting(0.0, ge=0, help="Metres those closures must span on each robot's map: longer than the "
                                               "world's longest look-alike stretch (the campus preset: 25); 0: any.")
    closure_gate: float = setting(3.0, gt=0, help="Largest innovation, standard deviations, of an inter-robot closure "
                                                  "between joined maps.")
    kernel_width: float = setting(1.0, gt=0, help="Cauchy kernel of each robot's own closures, standard deviations.")
    pending_limit: int = setting(60, ge=2, help="Pending closures between two parts weighed together (the newest).")
    closure_iterations: int = setting(4, ge=0, help="Extra solver iterations after a closure while they relinearize.")

    def check(self) -> None:
        check(self)


@dataclass
class RobotMap:
    """What the fleet map holds of one robot's map."""

    name: str
    slot: int
    poses: list[tuple[float, float, float]] = field(default_factory=list)   # in its own map, as first heard
    created: list[int] = field(default_factory=list)                        # each experience's frame
    links: int = 0                                                          # links taken
    aliased: set[int] = field(default_factory=set)                          # experiences with a look-alike


@dataclass
class Closure:
    """An inter-robot closure as the fleet map holds it: the link from the matched robot's
    experience (the place) to the revisiting robot's (its frame), and what became of it."""

    robot: str
    index: int
    frame: int
    experience: int
    matched_robot: str
    matched_frame: int
    matched_experience: int
    link: tuple[float, float, float]
    covariance: np.ndarray
    fate: str = "pending"
    statistic: float | None = None

    @property
    def ident(self) -> tuple[str, int]:
        return self.robot, self.index


@dataclass(frozen=True)
class ClosureInput:
    """A confirmed inter-robot closure placed on both maps: ``robot``'s frame ``frame`` at
    ``offset`` from its experience ``experience`` revisits ``matched_robot``'s place stored at
    ``matched_frame``, at ``matched_offset`` from its experience ``matched_experience``;
    ``relative_pose`` the frame's pose in the place's body frame, ``covariance`` (forward, left,
    yaw) row-major; ``method`` empty when unmeasured."""

    robot: str
    index: int
    frame: int
    experience: int
    offset: tuple[float, float, float]
    matched_robot: str
    matched_frame: int
    matched_experience: int
    matched_offset: tuple[float, float, float]
    method: str = ""
    relative_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    covariance: tuple[float, ...] = ()


@dataclass
class Result:
    """What one input did to the fleet map."""

    new: list[tuple[str, int]] = field(default_factory=list)      # experiences added
    moved: list[tuple[str, int]] = field(default_factory=list)    # experiences moved beyond 1 mm / 0.1 mrad
    decided: list[Closure] = field(default_factory=list)          # closures whose fate was set or changed
    joined: list[str] = field(default_factory=list)               # robots joined to another part
    split: list[tuple[str, str]] = field(default_factory=list)    # robot pairs split apart


class FleetMap:
    def __init__(self, params: FleetParams = FleetParams(), consistency: ConsistencyParams = ConsistencyParams()):
        import gtsam   # the solver; the map's readers need the rest only

        params.check()
        consistency.check()
        self.gtsam = gtsam
        self.params, self.consistency = params, consistency
        self.robots: dict[str, RobotMap] = {}
        self.estimates: dict[str, np.ndarray] = {}     # per robot, (E, 3) poses in its part's frame
        self.part: dict[str, str] = {}                 # robot → the robot whose frame its part is in
        self.joined_at: dict[str, int] = {}            # robot → its frame when it joined the fleet frame
        self.latest: dict[str, int] = {}               # robot → its newest frame the map has heard of
        self.placed_at: dict[str, int] = {}            # robot → its newest frame heard when it joined the fleet frame
        self.closures: list[Closure] = []
        self._closure_at: dict[tuple[str, int], int] = {}
        self.priors: dict[str, float] = {}             # robot → the sigma of its first experience's prior
        self.factors: list[tuple] = []                 # (kind, robot, source key, target key, transform, covariance)
        self.updates = 0                               # solver updates since the solver was (re)built
        kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(params.kernel_width)
        self._kernel = kernel
        self._rebuild()

    # --- inputs ---------------------------------------------------------------------------------
    def add_map(self, robot: str, experiences: list[tuple[int, float, float, float, int]], links: list[tuple]) -> Result:
        """Grow ``robot``'s map: new experiences (id, x, y, heading, frame), dense and in order,
        and new links (source, target, dx, dy, dheading, loop_closure, accepted, covariance 9)
        in the order its map made them. ValueError when an experience is not the next one."""
        result = Result()
        state = self.robots.get(robot)
        if state is None:
            if not experiences or experiences[0][0] != 0:
                raise ValueError(f"robot {robot}: its map must start at experience 0")
            state = self.robots[robot] = RobotMap(robot, len(self.robots))
            self.estimates[robot] = np.zeros((0, 3))
            self.part[robot] = robot
            self.priors[robot] = PRIOR_SIGMA
            if self.frame_robot == robot:
                self.joined_at[robot] = self.placed_at[robot] = int(experiences[0][4])
        # The robot's map frame → its part's frame, from its newest experience (initial values only).
        carry = self._carry(robot)
        fresh = []
        for ident, x, y, heading, frame in experiences:
            if ident != len(state.poses):
                raise ValueError(f"robot {robot}: experience {ident} follows {len(state.poses) - 1}")
            state.poses.append((float(x), float(y), float(heading)))
            state.created.append(int(frame))
            self.latest[robot] = max(self.latest.get(robot, int(frame)), int(frame))
            fresh.append(compose(carry, (x, y, heading)) if carry is not None else (x, y, heading))
            result.new.append((robot, ident))
        if fresh:
            self.estimates[robot] = np.vstack([self.estimates[robot], np.array(fresh, dtype=float)])
            for ident in range(len(state.poses) - len(fresh), len(state.poses)):
                self._values.insert(self._key(robot, ident), self.gtsam.Pose2(*self.estimates[robot][ident]))
                if ident == 0:
                    self._graph.add(self._prior_factor(robot))
        closure = False
        for source, target, dx, dy, dheading, loop_closure, accepted, covariance in links:
            state.links += 1
            if not (0 <= source < len(state.poses) and 0 <= target < len(state.poses)):
                raise ValueError(f"robot {robot}: link {source} → {target} names an experience it does not have")
            covariance = np.array(covariance, dtype=float).reshape(3, 3)
            if loop_closure and not accepted:
                state.aliased.update((int(source), int(target)))
                continue
            kind = "closure" if loop_closure else "odometry"
            entry = (kind, robot, self._key(robot, source), self._key(robot, target), (dx, dy, dheading), covariance)
            self.factors.append(entry)
            self._graph.add(self._factor(entry))
            closure = closure or loop_closure
            if not loop_closure and target >= len(state.poses) - len(fresh):   # a new experience: composed from its source
                self.estimates[robot][target] = compose(tuple(self.estimates[robot][source]), (dx, dy, dheading))
                self._values.update(self._key(robot, target), self.gtsam.Pose2(*self.estimates[robot][target]))
        if closure:
            self._solve(result)
        return result

    def add_closure(self, closure: ClosureInput) -> Result:
        """Take one inter-robot closure (module docstring); a closure already taken is ignored."""
        result = Result()
        if closure.robot == closure.matched_robot or (closure.robot, closure.index) in self._closure_at:
            return result
        for name, ident in ((closure.robot, closure.experience), (closure.matched_robot, closure.matched_experience)):
            if name not in self.robots or not 0 <= ident < len(self.robots[name].poses):
                raise ValueError(f"closure {closure.index} of robot {closure.robot}: robot {name} has no experience {ident}")
        self.latest[closure.robot] = max(self.latest.get(closure.robot, closure.frame), closure.frame)
        link, covariance = _link_of(closure)
        entry = Closure(closure.robot, closure.index, closure.frame, closure.experience, closure.matched_robot,
                        closure.matched_frame, closure.matched_experience, link, covariance)
        self._closure_at[entry.ident] = len(self.closures)
        self.closures.append(entry)
        if not closure.method or len(closure.covariance) != 9 or closure.method != "stereo":
            entry.fate = "unmeasured"   # (a monocular closure has no length: nothing to say where a robot is)
        elif closure.experience in self.robots[closure.robot].aliased or \
                closure.matched_experience in self.robots[closure.matched_robot].aliased:
            entry.fate = "rejected"     # its robot's own map knows a look-alike of that place
        elif self.part[closure.robot] == self.part[closure.matched_robot]:
            self._flush()
            self._test(entry, result)
            if entry.fate == "rejected":
                self._maybe_split(closure.robot, closure.matched_robot, result)
        else:
            self._maybe_join(self.part[closure.matched_robot], self.part[closure.robot], result, entry)
        if entry not in result.decided:
            result.decided.append(entry)
        return result

    # --- results --------------------------------------------------------------------------------
    def pose(self, robot: str, experience: int, offset=(0.0, 0.0, 0.0)) -> tuple[float, float, float]:
        """A robot's pose at ``offset`` from its experience, in its part's frame."""
        return compose(tuple(self.estimates[robot][experience]), offset)

    def joined(self, robot: str) -> bool:
        """Whether ``robot``'s map is in the fleet frame."""
        frame = self.frame_robot
        return frame is not None and self.part.get(robot) == self.part.get(frame)

    @property
    def frame_robot(self) -> str | None:
        if self.params.frame_robot:
            return self.params.frame_robot if self.params.frame_robot in self.robots else None
        return next(iter(self.robots), None)

    def final_poses(self) -> dict[str, np.ndarray]:
        """Every experience's best estimate, per robot (a pass over the map)."""
        self._flush()
        every, row, poses = self.gtsam.utilities.extractPose2(self._isam.calculateEstimate()), 0, {}
        for robot, state in sorted(self.robots.items(), key=lambda item: item[1].slot):
            poses[robot] = every[row:row + len(state.poses)].reshape(-1, 3).copy()
            row += len(state.poses)
        return poses

    def counts(self) -> dict[str, int]:
        counts = dict.fromkeys(FATES, 0)
        for closure in self.closures:
            counts[closure.fate] += 1
        return counts

    # --- joining and splitting --------------------------------------------------------------------
    def _maybe_join(self, fixed: str, moved: str, result: Result, newest: Closure | None = None) -> None:
        """Join the parts ``fixed`` and ``moved`` (anchor robots) when their pending closures hold
        a set that may join them (module docstring)."""
        pending = [c for c in self.closures if c.fate == "pending" and {self.part[c.robot], self.part[c.matched_robot]}
                   == {fixed, moved}][-self.params.pending_limit:]
        if len(pending) < self.params.join_closures:
            return
        candidates = [self._candidate(i, c) for i, c in enumerate(pending)]
        neighbours = consistency_graph(candidates, self.consistency)
        best = maximum_clique(neighbours)
        if len(best) < self.params.join_closures or self._span(pending, best) < self.params.join_span:
            return
        rivals = {k for k in neighbours if k not in best and not set(best) <= neighbours[k] | {k}}
        rival = maximum_clique(neighbours, rivals)
        if len(rival) >= self.params.join_closures and len(rival) * 2 > len(best):
            return   # two sets disagree on where the robots are: wait for more evidence
        self._join([pending[k] for k in best], result)
        self._test_pending(result)

    def _test_pending(self, result: Result) -> None:
        """Test the pending closures whose two robots are in one part now."""
        for closure in [c for c in self.closures if c.fate == "pending"]:
            if self.part[closure.robot] == self.part[closure.matched_robot]:
                self._test(closure, result)

    def _join(self, chosen: list[Closure], result: Result) -> None:
        first = chosen[0]
        a, b = self.part[first.matched_robot], self.part[first.robot]
        keep, move = sorted((a, b), key=self._seniority)
        # Where `move`'s part is in `keep`'s frame, from the best-measured closure of the set.
        best = min(chosen, key=lambda c: float(np.trace(c.covariance)))
        source = tuple(self.estimates[best.matched_robot][best.matched_experience])
        target = tuple(self.estimates[best.robot][best.experience])
        implied = compose(source, best.link)                # where the revisiting experience is in the place's part
        transform = compose(implied, inverse(target))       # the revisiting part's frame → the place's part's frame
        if self.part[best.robot] == keep:                   # the place's part moves instead
            transform = inverse(transform)
        members = [robot for robot, part in self.part.items() if part == move]
        for robot in members:
            self.estimates[robot] = np.array([compose(transform, tuple(p)) for p in self.estimates[robot]]).reshape(-1, 3)
            self.part[robot] = keep
            self.priors[robot] = JOINED_PRIOR_SIGMA
            result.joined.append(robot)
            result.moved.extend((robot, i) for i in range(len(self.estimates[robot])))
        for closure in chosen:
            closure.fate = "accepted"
            closure.statistic = None
            result.decided.append(closure)
        if self.joined(members[0]):
            for robot in members:
                frames = [c.frame if c.robot == robot else c.matched_frame for c in chosen
                          if robot in (c.robot, c.matched_robot)]
                self.joined_at[robot] = max(frames) if frames else self.robots[robot].created[-1]
                # when it was placed: its newest frame the map had heard of (a closure's frame of the
                # robot as the place's, in joined_at, may be long past)
                self.placed_at[robot] = max(self.joined_at[robot], self.latest.get(robot, self.joined_at[robot]))
        self._rebuild(result)

    def _maybe_split(self, one: str, other: str, result: Result) -> None:
        between_them = [c for c in self.closures if {c.robot, c.matched_robot} == {one, other} and c.fate in
                        ("accepted", "rejected") and c.experience not in self.robots[c.robot].aliased
                        and c.matched_experience not in self.robots[c.matched_robot].aliased]
        refused = [c for c in between_them if c.fate == "rejected"][-self.params.pending_limit:]
        accepted = [c for c in between_them if c.fate == "accepted"]
        if len(refused) <= max(2 * len(accepted), self.params.join_closures - 1):
            return
        candidates = [self._candidate(i, c) for i, c in enumerate(refused)]
        best = maximum_clique(consistency_graph(candidates, self.consistency))
        if len(best) <= 2 * len(accepted) or len(best) < self.params.join_closures or \
                self._span(refused, best) < self.params.join_span:
            return
        # The evidence against the join outweighs the evidence for it: undo it and decide again.
        for closure in between_them:
            closure.fate, closure.statistic = "pending", None
            result.decided.append(closure)
        result.split.append((one, other))
        self._reparts(result)
        self._rebuild(result)
        if self.part[one] == self.part[other]:   # still joined through another robot
            self._test_pending(result)
        else:
            self._maybe_join(self.part[one], self.part[other], result)

    def _reparts(self, result: Result) -> None:
        """The parts again from the accepted closures (after a split), each part in the frame of
        its most senior robot, which holds it with a firm prior again (a part cut off from the
        frame it was moved into goes back to its own robot's map frame)."""
        order = sorted(self.robots, key=self._seniority)
        adjacency = {robot: set() for robot in order}
        for c in self.closures:
            if c.fate == "accepted":
                adjacency[c.robot].add(c.matched_robot)
                adjacency[c.matched_robot].add(c.robot)
        seen: set[str] = set()
        for robot in order:
            if robot in seen:
                continue
            group, stack = [], [robot]
            while stack:
                name = stack.pop()
                if name in seen:
                    continue
                seen.add(name)
                group.append(name)
                stack.extend(sorted(adjacency[name] - seen))
            if self.priors[robot] != PRIOR_SIGMA:   # it had been moved into another part's frame: back to its own
                back = compose(self.robots[robot].poses[0], inverse(tuple(self.estimates[robot][0])))
                for name in group:
                    self.estimates[name] = np.array([compose(back, tuple(p)) for p in self.estimates[name]]).reshape(-1, 3)
                    result.moved.extend((name, i) for i in range(len(self.estimates[name])))
            for name in group:
                self.part[name] = robot
                self.priors[name] = PRIOR_SIGMA if name == robot else JOINED_PRIOR_SIGMA
        for name in list(self.joined_at):
            if not self.joined(name):
                del self.joined_at[name]
                self.placed_at.pop(name, None)

    def _seniority(self, robot: str) -> tuple[int, int]:
        return (0 if robot == self.frame_robot else 1, self.robots[robot].slot)

    def _candidate(self, key: int, closure: Closure) -> Candidate:
        return Candidate(key, tuple(self.estimates[closure.matched_robot][closure.matched_experience]),
                         tuple(self.estimates[closure.robot][closure.experience]), closure.link, closure.covariance)

    def _span(self, closures: list[Closure], chosen: list[int]) -> float:
        """The smaller of the distances the chosen closures span on either robot's map."""
        if len(chosen) < 2:
            return 0.0
        ends = [np.array([self.estimates[closures[k].matched_robot][closures[k].matched_experience][:2] for k in chosen]),
                np.array([self.estimates[closures[k].robot][closures[k].experience][:2] for k in chosen])]
        return float(min(np.max(np.hypot(*(points[:, None, :] - points[None, :, :]).transpose(2, 0, 1))) for points in ends))

    # --- the solver -----------------------------------------------------------------------------
    def _key(self, robot: str, experience: int) -> int:
        return self.robots[robot].slot * SLOT + int(experience)

    def _carry(self, robot: str) -> tuple[float, float, float] | None:
        """The transform from the robot's map frame to its part's, by its newest experience."""
        state = self.robots[robot]
        if not state.poses:
            return None
        return compose(tuple(self.estimates[robot][-1]), inverse(state.poses[-1]))

    def _prior_factor(self, robot: str):
        gtsam = self.gtsam
        return gtsam.PriorFactorPose2(self._key(robot, 0), gtsam.Pose2(*self.robots[robot].poses[0]) if self.priors[robot]
                                      == PRIOR_SIGMA and self.part[robot] == robot else
                                      gtsam.Pose2(*self.estimates[robot][0]),
                                      gtsam.noiseModel.Isotropic.Sigma(3, self.priors[robot]))

    def _factor(self, entry, robust: bool | None = None):
        kind, _, source, target, transform, covariance = entry
        noise = self.gtsam.noiseModel.Gaussian.Covariance(covariance)
        # A robot's own closures keep the robot's kernel; the inter-robot closures stay Gaussian: they
        # are the parts' only links, and a later closure's test must see them as firm (a kernel on
        # them lets one false closure swing the whole part and pass its own test).
        if robust if robust is not None else kind == "closure":
            noise = self.gtsam.noiseModel.Robust.Create(self._kernel, noise)
        return self.gtsam.BetweenFactorPose2(source, target, self.gtsam.Pose2(*transform), noise)

    def _closure_entry(self, closure: Closure) -> tuple:
        return ("inter", closure.robot, self._key(closure.matched_robot, closure.matched_experience),
                self._key(closure.robot, closure.experience), closure.link, closure.covariance)

    def _new_isam(self):
        params = self.gtsam.ISAM2Params()
        params.setFactorization("QR")
        params.relinearizeSkip = 1
        params.setRelinearizeThreshold(0.01)
        return self.gtsam.ISAM2(params)

    def _rebuild(self, result: Result | None = None) -> None:
        """A fresh solver holding every factor at the current estimates (a join, a split, a rebase)."""
        gtsam = self.gtsam
        self._isam = self._new_isam()
        self._graph, self._values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for robot, state in self.robots.items():
            for ident in range(len(state.poses)):
                self._values.insert(self._key(robot, ident), gtsam.Pose2(*self.estimates[robot][ident]))
            if state.poses:
                self._graph.add(self._prior_factor(robot))
        for entry in self.factors:
            self._graph.add(self._factor(entry))
        for closure in self.closures:
            if closure.fate == "accepted":
                self._graph.add(self._factor(self._closure_entry(closure)))
        self.updates = 0
        if self._values.size():
            self._solve(result or Result())

    def _flush(self) -> None:
        if self._graph.size() or self._values.size():
            self._update()

    def _update(self, remove: list[int] | None = None):
        update = self._isam.update(self._graph, self._values, remove or [])
        self._graph, self._values = self.gtsam.NonlinearFactorGraph(), self.gtsam.Values()
        self.updates += 1
        return update

    def _solve(self, result: Result, remove: list[int] | None = None):
        first = update = self._update(remove)
        for _ in range(self.params.closure_iterations):
            if not update.getVariablesRelinearized():
                break
            update = self._update()
        self._refresh(result)
        return first

    def _refresh(self, result: Result) -> None:
        """Every experience's estimate from the solver, in one pass (keys sort by robot, then experience)."""
        every = self.gtsam.utilities.extractPose2(self._isam.calculateEstimate())
        row = 0
        for robot, state in sorted(self.robots.items(), key=lambda item: item[1].slot):
            count = len(state.poses)
            fresh = every[row:row + count]
            row += count
            result.moved.extend((robot, int(i)) for i in _moved(fresh, self.estimates[robot]))
            self.estimates[robot] = fresh.copy()

    def _test(self, closure: Closure, result: Result) -> None:
        """The robust test of a closure between joined parts (module docstring)."""
        gtsam = self.gtsam
        entry = self._closure_entry(closure)
        _, _, source, target, transform, covariance = entry
        information = np.linalg.inv(covariance)
        measured = gtsam.Pose2(*transform)
        before = {robot: estimates.copy() for robot, estimates in self.estimates.items()}
        innovation = gtsam.Pose2.Logmap(measured.between(
            self._isam.calculateEstimatePose2(source).between(self._isam.calculateEstimatePose2(target))))
        self._graph.add(self._factor(entry, robust=False))
        index = self._solve(result).getNewFactorsIndices()[-1]
        residual = gtsam.Pose2.Logmap(measured.between(
            self._isam.calculateEstimatePose2(source).between(self._isam.calculateEstimatePose2(target))))
        statistic = float(innovation @ information @ residual)
        accepted = float(residual @ information @ residual) - LINEAR_TOLERANCE <= statistic <= self.params.closure_gate ** 2
        closure.statistic = float(math.sqrt(max(statistic, 0.0)))
        if accepted:   # kept, as a Gaussian factor (not the test's)
            self._graph.add(self._factor(entry))
        self._solve(result, remove=[index])
        if not accepted and any(_moved(self.estimates[robot], estimates).size for robot, estimates in before.items()):
            # A far-off closure bends the map so much that taking it out again leaves it in another
            # minimum (the robots' own closures, under their kernel, then hold the bent shape): the
            # map as it was before the test, solved afresh.
            self.estimates = before
            self._rebuild(result)
        closure.fate = "accepted" if accepted else "rejected"
        result.decided.append(closure)

    # --- checkpoints ----------------------------------------------------------------------------
    def state(self) -> dict:
        """The map's whole state (JSON-able lists and arrays): what `restore` takes."""
        self._flush()
        return {"robots": [{"name": s.name, "slot": s.slot, "poses": [list(p) for p in s.poses], "created": s.created,
                            "links": s.links, "aliased": sorted(s.aliased)} for s in self.robots.values()],
                "estimates": {robot: e.tolist() for robot, e in self.estimates.items()},
                "part": dict(self.part), "joined_at": dict(self.joined_at), "latest": dict(self.latest),
                "placed_at": dict(self.placed_at),
                "priors": dict(self.priors),
                "factors": [[kind, robot, int(s), int(t), list(tr), np.asarray(c).ravel().tolist()]
                            for kind, robot, s, t, tr, c in self.factors],
                "closures": [{**{f.name: getattr(c, f.name) for f in dataclasses.fields(c) if f.name != "covariance"},
                              "link": list(c.link), "covariance": np.asarray(c.covariance).ravel().tolist()}
                             for c in self.closures]}

    def rebase(self) -> dict:
        """Rebuild the solver at the current estimates and return the state: from here on this
        map and `restore(params, state)` are the same map."""
        state = self.state()
        self._rebuild()
        return state

    @classmethod
    def restore(cls, params: FleetParams, consistency: ConsistencyParams, state: dict) -> FleetMap:
        fleet = cls(params, consistency)
        for r in state["robots"]:
            fleet.robots[r["name"]] = RobotMap(r["name"], int(r["slot"]), [tuple(p) for p in r["poses"]],
                                               [int(v) for v in r["created"]], int(r["links"]), set(r["aliased"]))
        fleet.estimates = {robot: np.array(e, dtype=float).reshape(-1, 3) for robot, e in state["estimates"].items()}
        fleet.part, fleet.joined_at, fleet.priors = dict(state["part"]), dict(state["joined_at"]), dict(state["priors"])
        fleet.latest, fleet.placed_at = dict(state["latest"]), dict(state["placed_at"])
        fleet.factors = [(kind, robot, int(s), int(t), tuple(tr), np.array(c, dtype=float).reshape(3, 3))
                         for kind, robot, s, t, tr, c in state["factors"]]
        for record in state["closures"]:
            closure = Closure(**{**record, "link": tuple(record["link"]),
                                 "covariance": np.array(record["covariance"], dtype=float).reshape(3, 3)})
            fleet._closure_at[closure.ident] = len(fleet.closures)
            fleet.closures.append(closure)
        fleet._rebuild()
        return fleet


def _moved(estimates: np.ndarray, before: np.ndarray) -> np.ndarray:
    """The rows of ``estimates`` more than MOVED from ``before``'s (headings wrapped)."""
    change = np.abs(estimates - before)
    change[:, 2] = np.abs((change[:, 2] + np.pi) % (2 * np.pi) - np.pi)
    return np.flatnonzero((change > MOVED).any(axis=1))


def _link_of(closure: ClosureInput) -> tuple[tuple[float, float, float], np.ndarray]:
    """The link from the place's experience to the revisiting frame's, and its covariance (right
    tangent): matched_offset ∘ relative_pose ∘ offset⁻¹; the measurement's noise, taken from its
    components (forward, left, yaw) to the tangent, carried across the frame's offset."""
    measurement = closure.relative_pose
    link = compose(compose(closure.matched_offset, measurement), inverse(closure.offset))
    if len(closure.covariance) != 9:
        return link, np.eye(3)
    covariance = np.array(closure.covariance, dtype=float).reshape(3, 3)
    c, s = math.cos(measurement[2]), math.sin(measurement[2])
    to_tangent = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    carry = adjoint(closure.offset)
    tangent = carry @ to_tangent @ covariance @ to_tangent.T @ carry.T
    return link, (tangent + tangent.T) / 2 + np.diag([1e-6, 1e-6, 1e-8])
