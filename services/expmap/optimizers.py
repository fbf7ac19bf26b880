"""The experience map's optimisers: what places the experiences, given its links (graph.py).

- `PoseGraph` (`optimizer = "gtsam"`): the map as a pose graph solved incrementally by gtsam's
  iSAM2 (Kaess et al., IJRR 2012), QR factorisation (stable on long chains where the default
  Cholesky failed in a trial). Odometric links are Gaussian factors with the covariance of the
  odometry they span. A closure is tested against the graph: it is added as a Gaussian factor
  and the graph solved; the rise of the graph's χ² it caused is its test statistic — for a
  linear problem exactly the innovation's Mahalanobis norm νᵀS⁻¹ν, the difference between the
  relative pose the closure measures and the one the map predicted, weighed by the closure's
  covariance and the map's own uncertainty between its two experiences (S). It is computed from
  the two experiences alone: with r the closure's residual after solving, S⁻¹ν = Σ⁻¹r, so
  νᵀS⁻¹ν = νᵀΣ⁻¹r — no marginal covariance (a pass down the Bayes tree), no error of the whole
  graph. Within `closure_gate` standard deviations the closure is accepted and kept under a
  robust kernel (Cauchy by default, `kernel_width` standard deviations wide), so that a closure
  that later proves wrong pulls little; beyond, the odometry contradicts it: it is removed and
  the graph settles back, so a refused closure does not bend the map.
  The graph is solved only on frames with a closure: between closures the map is a chain, and
  a new experience's estimate is its predecessor's composed with the odometry, exactly what the
  solver would give, so such frames cost nothing that grows with the map. (An iSAM2 update
  costs some time proportional to the map in gtsam 4.3 — its Bayes-tree destructor visits every
  clique below the part it re-eliminates: microseconds per thousand experiences, docs/mapping.md.)
- `Relaxation` (`optimizer = "ratslam"`): RatSLAM's graph relaxation. Every link pulls both of
  its ends toward agreement with its transform by `correction` (0.5, as in RatSLAM) of the
  disagreement; headings the same way. All links act at once and a node's pulls are averaged
  over its links, so the result does not depend on link order and the vectorised update is
  stable. Every closure is accepted (the paper's model); a pass costs one sweep over all links.

Both write the map's published poses (ExperienceMap._poses) and report which experiences moved,
and both can be rebuilt from the map's state (`state`, `rebuild`: ExperienceMap.rebase). The pose
graph is rebuilt as a fresh iSAM2 given every factor the graph holds (the prior, the odometric
links, the accepted closures under their kernel) at the linearisation point it had, with the
experiences not yet in the solver at their composed poses, in a few updates, oldest first.
"""

from __future__ import annotations

import numpy as np

from services.common.geometry import wrap
from services.expmap.graph import MOVED, ExperienceMap, Link

# Published poses refreshed per solve besides those the solver re-eliminated: every solved
# experience is refreshed at least once every len(map) / REFRESH_PER_SOLVE solves.
REFRESH_PER_SOLVE = 256
PRIOR_SIGMA = 1e-6          # the first experience anchors the map frame to the odometry frame
RELINEARIZE_THRESHOLD = 0.01
LINEAR_TOLERANCE = 1e-6     # χ² units: rounding in the closure test's linear-regime check
REBUILD_PARTS = 8           # a rebuilt solver is given the graph in this many updates (PoseGraph.rebuild)


class PoseGraph:
    def __init__(self, experience_map: ExperienceMap):
        import gtsam   # imported here: the ratslam optimiser and the map's readers need no gtsam

        self.gtsam = gtsam
        self.map = experience_map
        self.isam = self._new_isam()
        self.covariances: list[np.ndarray] = []   # of each of the map's links, in its order
        # The first experience of each part of the graph → its prior (pose, std dev): firm for a part
        # on its own, weak once closures joined it (it then only keeps the solve determinate).
        self._priors: dict[int, tuple[tuple[float, float, float], float]] = {}
        self._factors = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._solved = 0                    # experiences 0.._solved-1 are in the solver
        self._refresh: set[int] = set()     # experiences whose estimate the last updates touched
        self._cursor = 0                    # round-robin refresh position
        self.updates = 0                    # solver updates since the solver was (re)built
        self._tested = False                # a closure was tested since the last solve(): its estimates are newer
        p = experience_map.params
        kernels = {"cauchy": gtsam.noiseModel.mEstimator.Cauchy, "geman_mcclure": gtsam.noiseModel.mEstimator.GemanMcClure,
                   "dcs": gtsam.noiseModel.mEstimator.DCS, "huber": gtsam.noiseModel.mEstimator.Huber}
        self._kernel = kernels[p.robust_kernel].Create(p.kernel_width) if p.robust_kernel in kernels else None

    def _new_isam(self):
        params = self.gtsam.ISAM2Params()
        params.setFactorization("QR")
        params.relinearizeSkip = 1
        params.setRelinearizeThreshold(RELINEARIZE_THRESHOLD)
        params.enablePartialRelinearizationCheck = True
        return self.gtsam.ISAM2(params)

    # --- building ---------------------------------------------------------------------------------
    def add_experience(self, index: int, pose, anchor: bool = False) -> None:
        """A new experience; ``anchor`` (or the first): it starts a part of the graph, held where
        its pose is by a prior."""
        self._values.insert(index, self.gtsam.Pose2(*pose))
        if index == 0 or anchor:
            self._priors[index] = (tuple(pose), PRIOR_SIGMA)
            self._factors.add(self._prior_factor(index))

    def add_link(self, link: Link, covariance: np.ndarray) -> None:
        self.covariances.append(covariance)
        self._factors.add(self._factor(link, self.gtsam.noiseModel.Gaussian.Covariance(covariance)))

    def add_refused(self, covariance: np.ndarray) -> None:
        """A closure link kept as evidence only, refused without a test (it joined nothing)."""
        self.covariances.append(covariance)

    def add_closure(self, link: Link, covariance: np.ndarray) -> tuple[bool, float]:
        """Test a closure against the graph and keep it when it passes; (accepted, test statistic
        in standard deviations)."""
        self.covariances.append(covariance)
        information = np.linalg.inv(covariance)
        # The prediction: the published pose of the source (what the frame was composed from)
        # and the solver's estimate of the target; after another closure of the same frame was
        # tested, the published poses lag the solver's, so both ends come from the solver.
        source = self.isam.calculateEstimatePose2(link.source) if self._tested and link.source < self._solved \
            else self._pose(link.source)
        innovation = self._residual(link, source, self.isam.calculateEstimatePose2(link.target)
                                    if link.target < self._solved else self._pose(link.target))
        self._factors.add(self._factor(link, self.gtsam.noiseModel.Gaussian.Covariance(covariance)))
        index = self._solve().getNewFactorsIndices()[-1]
        residual = self._residual(link, *(self.isam.calculateEstimatePose2(key) for key in (link.source, link.target)))
        statistic = float(innovation @ information @ residual)
        # For a linear problem νᵀΣ⁻¹r ≥ rᵀΣ⁻¹r ≥ 0. Less means the solve left the linear regime (a
        # closure metres from where the map puts it tears the map apart to satisfy it): refused.
        accepted = float(residual @ information @ residual) - LINEAR_TOLERANCE <= statistic <= self.map.params.closure_gate ** 2
        statistic = float(np.sqrt(max(statistic, 0.0)))
        if accepted and self._kernel is not None:   # kept under the robust kernel
            self._factors.add(self._closure_factor(link, covariance))
            self._update(remove=[index])
        elif not accepted:   # refused: out of the graph, and the estimate settles back without it
            self._solve(remove=[index])
        self._tested = True
        return accepted, statistic

    def _solve(self, remove: list[int] | None = None):
        """An update, then more (up to closure_iterations) while they still relinearize something."""
        first = result = self._update(remove)
        for _ in range(self.map.params.closure_iterations):
            if not result.getVariablesRelinearized():
                break
            result = self._update()
        return first

    def _pose(self, key: int):
        return self.gtsam.Pose2(*self.map.poses[key])

    def _residual(self, link: Link, source, target) -> np.ndarray:
        """The link's error Log(measured⁻¹ ∘ predicted) for these two poses (the factor's own)."""
        return self.gtsam.Pose2.Logmap(self.gtsam.Pose2(*link.transform).between(source.between(target)))

    def _factor(self, link: Link, noise):
        return self.gtsam.BetweenFactorPose2(link.source, link.target, self.gtsam.Pose2(*link.transform), noise)

    def _closure_factor(self, link: Link, covariance: np.ndarray):
        """An accepted closure's factor as the graph keeps it: under the robust kernel, if any."""
        noise = self.gtsam.noiseModel.Gaussian.Covariance(covariance)
        return self._factor(link, noise if self._kernel is None else self.gtsam.noiseModel.Robust.Create(self._kernel, noise))

    def _prior_factor(self, key: int):
        pose, sigma = self._priors[key]
        return self.gtsam.PriorFactorPose2(key, self.gtsam.Pose2(*pose), self.gtsam.noiseModel.Isotropic.Sigma(3, sigma))

    # --- rebuilding -------------------------------------------------------------------------------
    def state(self) -> dict[str, np.ndarray]:
        """The solver's part of the map's state: linearisation point (the composed pose of an
        experience not yet in the solver), the prior, the links' covariances, the refresh plan."""
        solved = self.gtsam.utilities.extractPose2(self.isam.getLinearizationPoint()) if self._solved else np.zeros((0, 3))
        pending = range(self._solved, len(self.map))   # the next update would have refreshed them
        priors = np.array([(key, *pose, sigma) for key, (pose, sigma) in sorted(self._priors.items())],
                          dtype=float).reshape(-1, 5)
        return {"theta": np.concatenate([solved, self.map.poses[self._solved:]]), "prior": priors[0, 1:4],
                "part_priors": priors[1:],
                "covariances": np.array(self.covariances, dtype=float).reshape(-1, 3, 3),
                "refresh": np.array(sorted(self._refresh.union(pending)), dtype=np.int64),
                "refresh_cursor": np.array(self._cursor, dtype=np.int64)}

    def rebuild(self, state: dict[str, np.ndarray]) -> None:
        """A fresh iSAM2 holding the graph `state` and the map's links describe, given to it in
        REBUILD_PARTS updates, oldest experiences first. (In one update it would order the whole
        graph anew, and on a map that loops the updates after it re-eliminate far more: the 200
        frames after 8000 of the looping stack's journal took 61 ms a frame instead of 11. In
        parts, recent experiences stay near the root of the Bayes tree, as the live updates
        keep them: after 9000 frames, 10.0 ms a frame, 12.3 without a rebuild.)"""
        theta, covariances = state["theta"], state["covariances"]
        if len(theta) != len(self.map) or len(covariances) != len(self.map.links):
            raise ValueError("solver state of another map size")
        self._priors = {0: (tuple(float(v) for v in state["prior"]), PRIOR_SIGMA)}
        for key, x, y, heading, sigma in state.get("part_priors", np.zeros((0, 5))):
            self._priors[int(key)] = ((float(x), float(y), float(heading)), float(sigma))
        self.covariances = list(covariances)
        factors = [(key, self._prior_factor(key)) for key in self._priors]   # (the newest experience it links, factor)
        for link, covariance in zip(self.map.links, self.covariances):
            if link.accepted:
                factors.append((max(link.source, link.target), self._closure_factor(link, covariance) if link.loop_closure
                                else self._factor(link, self.gtsam.noiseModel.Gaussian.Covariance(covariance))))
        factors.sort(key=lambda item: item[0])
        self.isam = self._new_isam()
        size, added = -(-len(theta) // REBUILD_PARTS), 0
        for start in range(0, len(theta), size):
            graph, values = self.gtsam.NonlinearFactorGraph(), self.gtsam.Values()
            for key in range(start, min(start + size, len(theta))):
                values.insert(key, self.gtsam.Pose2(*theta[key]))
            while added < len(factors) and factors[added][0] < start + size:
                graph.add(factors[added][1])
                added += 1
            self.isam.update(graph, values)
        self._factors, self._values = self.gtsam.NonlinearFactorGraph(), self.gtsam.Values()
        self._solved = len(theta)
        self._refresh = {int(key) for key in state["refresh"]}
        self._cursor = int(state["refresh_cursor"])
        self.updates = 0

    def _update(self, remove: list[int] | None = None):
        result = self.isam.update(self._factors, self._values, remove or [])
        self._solved += self._values.size()
        self._factors, self._values = self.gtsam.NonlinearFactorGraph(), self.gtsam.Values()
        self._refresh.update(result.getMarkedKeys())
        self.updates += 1
        return result

    # --- results ----------------------------------------------------------------------------------
    def solve(self, closure_frame: bool) -> list[int]:
        """Refresh the published poses after a closure frame's solve: those the solver touched
        plus the next REFRESH_PER_SOLVE; the experiences that moved. Other frames solve nothing."""
        self._tested = False
        if not closure_frame or not self._solved:
            return []
        count = self._solved
        window = range(self._cursor, self._cursor + min(REFRESH_PER_SOLVE, count))
        self._cursor = (self._cursor + REFRESH_PER_SOLVE) % count
        # The current experience too: the experiences made until the next solve are composed from it.
        keys = sorted(key for key in self._refresh.union((i % count for i in window), [self.map.current]) if key < count)
        self._refresh.clear()
        poses, moved = self.map._poses, []
        for key in keys:
            estimate = self.isam.calculateEstimatePose2(key)
            pose = (estimate.x(), estimate.y(), estimate.theta())
            if (np.abs(poses[key] - pose) > MOVED).any():
                moved.append(key)
            poses[key] = pose
        return moved

    def estimate(self) -> np.ndarray:
        if self._factors.size() or self._values.size():
            self._update()
        if len(self.map) == 0:
            return np.zeros((0, 3))
        return self.gtsam.utilities.extractPose2(self.isam.calculateEstimate())


class Relaxation:
    def __init__(self, experience_map: ExperienceMap):
        self.map = experience_map
        self._clear()

    def _clear(self) -> None:
        self._source = np.zeros(64, dtype=np.int64)
        self._target = np.zeros(64, dtype=np.int64)
        self._offset = np.zeros((64, 3))
        self._count = 0
        self._degree = np.zeros(64)
        self.updates = 0   # relaxations since the arrays were (re)built

    def add_experience(self, index: int, pose, anchor: bool = False) -> None:
        if index >= len(self._degree):
            self._degree = np.concatenate([self._degree, np.zeros_like(self._degree)])

    def add_link(self, link: Link, covariance: np.ndarray | None = None) -> None:
        if self._count == len(self._source):   # grow geometrically
            self._source, self._target = (np.concatenate([a, np.zeros_like(a)]) for a in (self._source, self._target))
            self._offset = np.concatenate([self._offset, np.zeros_like(self._offset)])
        self._source[self._count], self._target[self._count] = link.source, link.target
        self._offset[self._count] = link.transform
        self._count += 1
        self._degree[link.source] += 1
        self._degree[link.target] += 1

    def add_closure(self, link: Link, covariance: np.ndarray) -> tuple[bool, None]:
        self.add_link(link)
        return True, None

    def add_refused(self, covariance: np.ndarray) -> None:
        pass

    def state(self) -> dict[str, np.ndarray]:
        return {}   # the map's poses and links are all there is

    def rebuild(self, state: dict[str, np.ndarray]) -> None:
        self._clear()
        for index in range(len(self.map)):
            self.add_experience(index, None)
        for link in self.map.links:
            self.add_link(link)

    def solve(self, closure_frame: bool) -> list[int]:
        p = self.map.params
        before = self.map.poses.copy()
        self.relax(p.relax_passes if closure_frame else p.relax_every_frame)
        return np.flatnonzero((np.abs(self.map.poses - before) > MOVED).any(axis=1)).tolist()

    def relax(self, passes: int) -> None:
        """`passes` relaxation passes over every link."""
        if not self._count or passes <= 0:
            return
        poses = self.map.poses   # a view: relaxed in place
        source, target, offset = self._source[:self._count], self._target[:self._count], self._offset[:self._count]
        degree = np.maximum(self._degree[:len(poses)], 1.0)[:, None]
        correction = self.map.params.correction
        self.updates += 1
        for _ in range(passes):
            start = poses[source]
            c, s = np.cos(start[:, 2]), np.sin(start[:, 2])
            predicted = np.column_stack([start[:, 0] + c * offset[:, 0] - s * offset[:, 1],
                                         start[:, 1] + s * offset[:, 0] + c * offset[:, 1],
                                         start[:, 2] + offset[:, 2]])
            error = predicted - poses[target]
            error[:, 2] = wrap(error[:, 2])
            pull = np.zeros_like(poses)
            np.add.at(pull, target, error * correction)
            np.add.at(pull, source, -error * correction)
            poses += pull / degree
            poses[:, 2] = wrap(poses[:, 2])

    def estimate(self) -> np.ndarray:
        return self.map.poses.copy()
