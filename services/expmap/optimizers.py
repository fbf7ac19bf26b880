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

Both write the map's published poses (ExperienceMap._poses) and report which experiences moved.
"""

from __future__ import annotations

import numpy as np

from services.expmap.graph import MOVED, ExperienceMap, Link, wrap

# Published poses refreshed per solve besides those the solver re-eliminated: every solved
# experience is refreshed at least once every len(map) / REFRESH_PER_SOLVE solves.
REFRESH_PER_SOLVE = 256
PRIOR_SIGMA = 1e-6          # the first experience anchors the map frame to the odometry frame
RELINEARIZE_THRESHOLD = 0.01
LINEAR_TOLERANCE = 1e-6     # χ² units: rounding in the closure test's linear-regime check


class PoseGraph:
    def __init__(self, experience_map: ExperienceMap):
        import gtsam   # imported here: the ratslam optimiser and the map's readers need no gtsam

        self.gtsam = gtsam
        self.map = experience_map
        params = gtsam.ISAM2Params()
        params.setFactorization("QR")
        params.relinearizeSkip = 1
        params.setRelinearizeThreshold(RELINEARIZE_THRESHOLD)
        params.enablePartialRelinearizationCheck = True
        self.isam = gtsam.ISAM2(params)
        self._factors = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._solved = 0                    # experiences 0.._solved-1 are in the solver
        self._refresh: set[int] = set()     # experiences whose estimate the last updates touched
        self._cursor = 0                    # round-robin refresh position
        p = experience_map.params
        kernels = {"cauchy": gtsam.noiseModel.mEstimator.Cauchy, "geman_mcclure": gtsam.noiseModel.mEstimator.GemanMcClure,
                   "dcs": gtsam.noiseModel.mEstimator.DCS, "huber": gtsam.noiseModel.mEstimator.Huber}
        self._kernel = kernels[p.robust_kernel].Create(p.kernel_width) if p.robust_kernel in kernels else None

    # --- building ---------------------------------------------------------------------------------
    def add_experience(self, index: int, pose) -> None:
        self._values.insert(index, self.gtsam.Pose2(*pose))
        if index == 0:
            self._factors.add(self.gtsam.PriorFactorPose2(0, self.gtsam.Pose2(*pose),
                                                          self.gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))

    def add_link(self, link: Link, covariance: np.ndarray) -> None:
        self._factors.add(self._factor(link, self.gtsam.noiseModel.Gaussian.Covariance(covariance)))

    def add_closure(self, link: Link, covariance: np.ndarray) -> tuple[bool, float]:
        """Test a closure against the graph and keep it when it passes; (accepted, test statistic
        in standard deviations)."""
        information = np.linalg.inv(covariance)
        innovation = self._residual(link, self._pose(link.source), self.isam.calculateEstimatePose2(link.target)
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
            self._factors.add(self._factor(link, self.gtsam.noiseModel.Robust.Create(
                self._kernel, self.gtsam.noiseModel.Gaussian.Covariance(covariance))))
            self._update(remove=[index])
        elif not accepted:   # refused: out of the graph, and the estimate settles back without it
            self._solve(remove=[index])
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

    def _update(self, remove: list[int] | None = None):
        result = self.isam.update(self._factors, self._values, remove or [])
        self._solved += self._values.size()
        self._factors, self._values = self.gtsam.NonlinearFactorGraph(), self.gtsam.Values()
        self._refresh.update(result.getMarkedKeys())
        return result

    # --- results ----------------------------------------------------------------------------------
    def solve(self, closure_frame: bool) -> list[int]:
        """Refresh the published poses after a closure frame's solve: those the solver touched
        plus the next REFRESH_PER_SOLVE; the experiences that moved. Other frames solve nothing."""
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
        self._source = np.zeros(64, dtype=np.int64)
        self._target = np.zeros(64, dtype=np.int64)
        self._offset = np.zeros((64, 3))
        self._count = 0
        self._degree = np.zeros(64)

    def add_experience(self, index: int, pose) -> None:
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
