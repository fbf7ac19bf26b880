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
  solver would give, so such frames cost nothing that grows with the map.
  The solver holds only the *junctions*: the first experience of each part of the graph (the
  map's, and a later session's until closures join it: graph.py; each held by its prior, made
  weak on the join), the two ends of every closure tested, an experience two chains leave
  (RatSLAM's snap). Between two junctions the map is a chain of odometric links whose inner
  experiences have no other factor; it enters the solver as one factor between its ends, the
  links composed and their covariances carried along it. That
  is exactly the graph with the inner experiences eliminated where the chain is straight, and to
  second order where the closures bend it: a chain's factor is relinearised (`_chain_factors_at`)
  when its ends move relative to each other as iSAM2 relinearises a variable. An inner
  experience is placed by its chain's own least squares given both ends (`_solution`); a closure
  that lands inside a chain splits it. (gtsam 4.3's iSAM2 visits every clique of its Bayes tree
  below what an update re-eliminates — the tree's destructor, and findFluid when it relinearises —
  so a solver holding every experience pays in proportion to the map on every update; holding the
  junctions, in proportion to the places closures have joined. docs/mapping.md, "Cost: flat per
  frame".)
- `Relaxation` (`optimizer = "ratslam"`): RatSLAM's graph relaxation. Every link pulls both of
  its ends toward agreement with its transform by `correction` (0.5, as in RatSLAM) of the
  disagreement; headings the same way. All links act at once and a node's pulls are averaged
  over its links, so the result does not depend on link order and the vectorised update is
  stable. Every closure is accepted (the paper's model); a pass costs one sweep over all links.

Both see of the map what `PlacedMap` names (graph.ExperienceMap is one), publish its poses
through its `place` and report which experiences moved (beyond links.MOVED), and both can be rebuilt from the map's state (`state`, `rebuild`: ExperienceMap.rebase). The pose
graph is rebuilt as a fresh iSAM2 given every factor the graph holds (the priors, the chains' as
they were linearised, the accepted closures under their kernel) with the junctions at the
estimates they had, in a few updates, oldest first; the chains are made again from the links.
"""

from __future__ import annotations

import bisect
from typing import Any, Protocol

import numpy as np

from services.common.geometry import compose, wrap
from services.expmap.links import MOVED, Link

# Published poses refreshed per solve besides those the solver re-eliminated: every solved
# experience is refreshed at least once every len(map) / REFRESH_PER_SOLVE solves.
REFRESH_PER_SOLVE = 256
PRIOR_SIGMA = 1e-6          # the first experience anchors the map frame to the odometry frame
# iSAM2 relinearises a junction whose estimate moved this far from its linearisation point (x, y
# in metres, heading in radians), and a chain's factor whose junctions moved this far relative
# to each other. The heading's is tighter: a factor between junctions far apart turns one by
# the other's heading times the distance between them.
RELINEARIZE_THRESHOLD = (0.01, 0.01, 0.001)
LINEAR_TOLERANCE = 1e-6     # χ² units: rounding in the closure test's linear-regime check
SETTLE_ITERATIONS = 20      # solver iterations at most, while they relinearize, after a refused closure is taken out
REBUILD_PARTS = 8           # a rebuilt solver is given the graph in this many updates (PoseGraph.rebuild)
PLACEMENT_ITERATIONS = 2    # Gauss–Newton steps of a chain's least squares (PoseGraph._solution)
BULK_ESTIMATE = 64          # junction estimates read from the solver one by one up to this many, else all at once


class PlacedMap(Protocol):
    """What an optimiser sees of the map it places: its parameters (graph.MapParams), its links
    in order, its experiences (len), the current one and the published poses, which it changes
    only through `place`."""

    params: Any
    links: list[Link]
    current: int | None

    def __len__(self) -> int: ...

    @property
    def poses(self) -> np.ndarray: ...

    def place(self, keys: np.ndarray, poses: np.ndarray) -> None: ...


class PoseGraph:
    def __init__(self, experience_map: PlacedMap):
        import gtsam  # imported here: the ratslam optimiser and the map's readers need no gtsam

        self.gtsam = gtsam
        self.map = experience_map
        p = experience_map.params
        kernels = {"cauchy": gtsam.noiseModel.mEstimator.Cauchy, "geman_mcclure": gtsam.noiseModel.mEstimator.GemanMcClure,
                   "dcs": gtsam.noiseModel.mEstimator.DCS, "huber": gtsam.noiseModel.mEstimator.Huber}
        self._kernel = kernels[p.robust_kernel].Create(p.kernel_width) if p.robust_kernel in kernels else None
        self.covariances: list[np.ndarray] = []   # of each of the map's links, in its order
        # The first experience of each part of the graph → its prior (pose, std dev): firm for a part
        # on its own, weak once closures joined it (it then only keeps the solve determinate).
        self._priors: dict[int, tuple[tuple[float, float, float], float]] = {}
        self._clear(64)

    def _clear(self, capacity: int) -> None:
        """An empty solver and empty chains for a map of up to `capacity` experiences (they grow)."""
        self.isam = self._new_isam()
        # Each experience's odometric link, from the experience it was made from (its parent).
        self._parent = np.full(capacity, -1, dtype=np.int64)
        self._step = np.zeros((capacity, 3))
        self._step_covariance = np.zeros((capacity, 3, 3))
        # The chains: an inner experience's lower junction (a junction: itself; -1: in the open
        # chain), a junction's upper junction and first inner experience, an open chain's
        # experience's pose in its upper junction's frame.
        self._bottom = np.full(capacity, -1, dtype=np.int64)
        self._top = np.full(capacity, -1, dtype=np.int64)
        self._first = np.zeros(capacity, dtype=np.int64)
        self._in_frame = np.zeros((capacity, 3))
        # Where a junction's chain factor was linearised: the relative pose of its two junctions
        # (NaN: at the chain's odometry, the factor it was made with).
        self._linearized = np.full((capacity, 3), np.nan)
        self._length = np.zeros(capacity)   # a junction's chain: the distance along it (m)
        # The chain at its odometry (the first step of `_solution`): a junction's chain composed (Z)
        # and its covariance (Σ_Z), each experience's Ad(d_k).
        self._composed = np.zeros((capacity, 3))
        self._chain_covariance = np.zeros((capacity, 3, 3))
        self._carry = np.zeros((capacity, 3, 3))
        self._junctions: list[int] = []                  # sorted
        self._open: tuple[int, int] | None = None         # (upper junction, first experience) of the open chain
        self._tip = (0.0, 0.0, 0.0)                       # its newest experience's pose in that junction's frame
        self._chain_factor: dict[int, int | None] = {}    # junction → its chain factor's index in the solver (None: pending)
        self._factors: list[tuple[int, object]] = []     # pending factors: (junction whose chain it is, or -1; factor)
        self._values = self.gtsam.Values()                # pending junctions
        self._remove: list[int] = []                      # pending removals
        self._refresh: set[int] = set()     # junctions whose estimate the last updates touched
        self._cursor = 0                    # round-robin refresh position
        self.updates = 0                    # solver updates since the solver was (re)built

    def _grow(self, size: int) -> None:
        capacity = len(self._parent)
        if size <= capacity:
            return
        extra = max(size, 2 * capacity) - capacity   # geometrically: amortised O(1) per experience
        for name in ("_parent", "_step", "_step_covariance", "_bottom", "_top", "_first", "_in_frame", "_linearized",
                     "_length", "_composed", "_chain_covariance", "_carry"):
            array = getattr(self, name)
            fill = -1 if name in ("_parent", "_bottom", "_top") else np.nan if name == "_linearized" else 0
            setattr(self, name, np.concatenate([array, np.full((extra,) + array.shape[1:], fill, dtype=array.dtype)]))

    def _new_isam(self):
        params = self.gtsam.ISAM2Params()
        params.setFactorization("QR")
        params.relinearizeSkip = 1
        thresholds = self.gtsam.ISAM2ThresholdMap()   # by the keys' symbol character: ours are plain numbers
        thresholds.insert(("\0", np.array(RELINEARIZE_THRESHOLD, dtype=float)))
        params.setRelinearizeThreshold(thresholds)
        params.enablePartialRelinearizationCheck = True
        return self.gtsam.ISAM2(params)

    # --- building ---------------------------------------------------------------------------------
    def add_experience(self, index: int, pose, anchor: bool = False) -> None:
        """A new experience; the first, or an ``anchor`` (the first of a later part of the graph),
        is a junction held where its pose is by a prior. (The open chain of the part before it
        ends at the experience before: a junction.)"""
        self._grow(index + 1)
        if index == 0 or anchor:
            if self._open is not None:
                self._make_junction(index - 1, end=index)
            self._priors[index] = (tuple(pose), PRIOR_SIGMA)
            self._bottom[index] = index
            self._junctions.append(index)
            self._values.insert(index, self.gtsam.Pose2(*pose))
            self._factors.append((-1, self._prior_factor(index)))

    def add_link(self, link: Link, covariance: np.ndarray) -> None:
        """An odometric link, from the current experience to the new one it made."""
        self.covariances.append(covariance)
        source, new = link.source, link.target
        self._parent[new], self._step[new], self._step_covariance[new] = source, link.transform, covariance
        if self._open is not None and source == new - 1 and self._bottom[source] < 0:   # the open chain goes on
            self._tip = compose(self._tip, link.transform)
            self._in_frame[new] = self._tip
            return
        # A chain starts at a junction. (The map makes new experiences from the newest one or, after
        # a snap, from a closure's end, a junction; the other cases keep the chains whole.)
        self._make_junction(source)
        if self._open is not None:
            self._make_junction(new - 1)
        self._open, self._tip = (source, new), link.transform
        self._in_frame[new] = link.transform

    def add_refused(self, covariance: np.ndarray) -> None:
        """A closure link kept as evidence only, refused without a test (it joined nothing)."""
        self.covariances.append(covariance)

    def add_closure(self, link: Link, covariance: np.ndarray) -> tuple[bool, float]:
        """Test a closure against the graph and keep it when it passes; (accepted, test statistic
        in standard deviations)."""
        self.covariances.append(covariance)
        information = np.linalg.inv(covariance)
        # The prediction: the solver's estimates of both experiences. (Their published poses can
        # lag them: after another closure of the frame was tested, or after a rebase, which solves
        # the graph afresh. A prediction from those is not the one the solve corrects, and the test
        # below would take the difference for a solve out of the linear regime.)
        estimates = self._poses_of(np.array([link.source, link.target]))
        innovation = self._residual(link, *(self.gtsam.Pose2(*pose) for pose in estimates))
        self._make_junction(link.source, estimates[0])
        self._make_junction(link.target, estimates[1])
        self._factors.append((-1, self._factor(link, self.gtsam.noiseModel.Gaussian.Covariance(covariance))))
        index = self._solve().getNewFactorsIndices()[-1]
        residual = self._residual(link, *(self.isam.calculateEstimatePose2(key) for key in (link.source, link.target)))
        statistic = float(innovation @ information @ residual)
        # For a linear problem νᵀΣ⁻¹r ≥ rᵀΣ⁻¹r ≥ 0. Less means the solve left the linear regime (a
        # closure metres from where the map puts it tears the map apart to satisfy it): refused.
        accepted = float(residual @ information @ residual) - LINEAR_TOLERANCE <= statistic <= self.map.params.closure_gate ** 2
        statistic = float(np.sqrt(max(statistic, 0.0)))
        if accepted and self._kernel is not None:   # kept under the robust kernel
            self._factors.append((-1, self._closure_factor(link, covariance)))
            self._update(remove=[index])
        elif not accepted:   # refused: out of the graph, and the estimate settles back without it
            # A closure metres off tears the map apart in the solve that tests it; the way back
            # from there takes more relinearizing steps than a solve of an accepted closure needs
            # (on the campus a look-alike 9584 standard deviations off left its frame's published
            # pose 6.7 m out after closure_iterations).
            self._solve(remove=[index], iterations=SETTLE_ITERATIONS)
        return accepted, statistic

    def _solve(self, remove: list[int] | None = None, iterations: int | None = None):
        """An update, then more (up to closure_iterations, or ``iterations``) while they still
        relinearize something (a junction, or a chain's factor: `_relinearize`)."""
        first = result = self._update(remove)
        for _ in range(self.map.params.closure_iterations if iterations is None else iterations):
            if not self._relinearize(result.getMarkedKeys()) and not result.getVariablesRelinearized():
                break
            result = self._update()
        return first

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

    # --- the chains -------------------------------------------------------------------------------
    def _make_junction(self, key: int, pose: np.ndarray | None = None, end: int | None = None) -> None:
        """Put an experience into the solver: the chain it is inside is split there (its factor
        replaced by those of its two parts), and it enters at its present estimate (`pose`).
        `end`: the open chain's end (exclusive) when it is not the map's newest experience."""
        if self._bottom[key] == key:
            return
        pose = self._poses_of(np.array([key]))[0] if pose is None else pose
        position = bisect.bisect_right(self._junctions, key)
        self._junctions.insert(position, key)
        if position + 1 < len(self._junctions):   # inside the chain of the next junction
            bottom = self._junctions[position + 1]
            top, first = int(self._top[bottom]), int(self._first[bottom])
            self._drop_chain_factor(bottom)
            self._factors.append((key, self._set_chain(key, top, first)))
            self._factors.append((bottom, self._set_chain(bottom, key, key + 1)))
        else:                                     # inside the open chain
            top, first = self._open
            self._factors.append((key, self._set_chain(key, top, first)))
            count = len(self.map) if end is None else end
            self._open = (key, key + 1) if key + 1 < count else None
            if self._open is not None:   # what is left of it starts at the new junction
                self._in_frame[key + 1:count] = _chain_poses(self._step[key + 1:count])
                self._tip = tuple(float(v) for v in self._in_frame[count - 1])
        self._values.insert(key, self.gtsam.Pose2(*pose))

    def _set_chain(self, junction: int, top: int, first: int):
        """The chain from junction `top` through experiences first..junction-1 to `junction`, and
        its factor: its odometry composed, Z = c_n (c_k: the pose of experience k in top's frame);
        a link's noise ε_k (right-hand, in k's frame) moves the junction by Ad(d_k) ε_k,
        d_k = Z⁻¹ c_k, so the factor's covariance is Σ_Z = Σ_k Ad(d_k) Σ_k Ad(d_k)ᵀ (for a single
        link, its own)."""
        self._top[junction], self._first[junction] = top, first
        pose = _chain_poses(self._step[first:junction + 1])
        carry = _adjoint(_between(pose[-1:], pose))
        accumulated = (carry @ self._step_covariance[first:junction + 1] @ carry.transpose(0, 2, 1)).sum(axis=0)
        covariance = 0.5 * (accumulated + accumulated.T)
        self._bottom[first:junction + 1] = junction
        self._chain_factor[junction] = None
        self._linearized[junction] = np.nan
        self._length[junction] = np.hypot(self._step[first:junction + 1, 0], self._step[first:junction + 1, 1]).sum()
        self._composed[junction], self._chain_covariance[junction], self._carry[first:junction + 1] = pose[-1], covariance, carry
        return self.gtsam.BetweenFactorPose2(top, junction, self.gtsam.Pose2(*pose[-1]),
                                             self.gtsam.noiseModel.Gaussian.Covariance(covariance))

    def _chain_factors_at(self, chains: np.ndarray, relative: np.ndarray) -> list:
        """The factors of these chains (lower junctions, ascending) linearised where their
        junctions are `relative` to each other: with the chain's own least squares there
        (`_solution`: noises ε̂, S and b = Σ A_k ε̂_k carried along the placed chain), the factor
        Log(M⁻¹ ∘ Δ) of covariance S with M = relative ∘ Exp(−b) has the value, slope and curvature
        of the chain's cost at Δ = relative: the graph with the chain's inner experiences
        eliminated, to second order there. (The odometry's factor is that only where the chain is
        not bent: with a misfit of 0.1 rad over a loop of 25 m it put the junctions' headings
        1e-4 rad and the inner experiences 1 mm from the optimum.)"""
        _, _, covariance, misfit = self._solution(chains, relative)
        measured = _compose(relative, _expmap(-misfit))
        factors = []
        for junction, pose, shape in zip(chains.tolist(), measured, covariance):
            self._linearized[junction] = relative[len(factors)]
            self._chain_factor[junction] = None
            factors.append(self.gtsam.BetweenFactorPose2(int(self._top[junction]), junction, self.gtsam.Pose2(*pose),
                                                         self.gtsam.noiseModel.Gaussian.Covariance(0.5 * (shape + shape.T))))
        return factors

    def _relinearize(self, marked) -> int:
        """Relinearise the factors of the chains (of more than one link) at these junctions whose
        junctions moved relative to each other by more than RELINEARIZE_THRESHOLD (in any tangent
        component) since the factor was linearised, as iSAM2 relinearises a variable; how many."""
        chains = self._chains_of(marked)
        chains = chains[self._first[chains] < chains]
        if not len(chains):
            return 0
        junctions = np.unique(np.concatenate([chains, self._top[chains]]))
        estimate = self._junction_poses(junctions)
        relative = _between(estimate[np.searchsorted(junctions, self._top[chains])], estimate[np.searchsorted(junctions, chains)])
        linearized = self._linearized[chains]
        raw = np.isnan(linearized[:, 0])
        linearized[raw] = self._composed[chains[raw]]   # at the odometry
        # A chain's heading counts by the distance along it: turning one end by θ moves the other by ℓθ.
        threshold = np.array(RELINEARIZE_THRESHOLD, dtype=float)
        moved = np.abs(_logmap(_between(linearized, relative)))
        moved[:, 2] *= np.maximum(self._length[chains] * threshold[2] / threshold[0], 1.0)
        due = (moved > threshold).any(axis=1)
        # Only where the odometry may bend so far (within closure_gate of its standard deviations):
        # a closure under test can tear the map metres apart, and the chains are not relinearised
        # at such a place, which the graph leaves again when it refuses the closure.
        misfit = _logmap(_between(self._composed[chains], relative))[..., None]
        plausible = (misfit.transpose(0, 2, 1) @ np.linalg.solve(self._chain_covariance[chains], misfit))[:, 0, 0] \
            <= self.map.params.closure_gate ** 2
        due &= plausible
        for junction in chains[due].tolist():
            self._drop_chain_factor(junction)
        if due.any():
            self._factors.extend(zip(chains[due].tolist(), self._chain_factors_at(chains[due], relative[due])))
        return int(due.sum())

    def _drop_chain_factor(self, junction: int) -> None:
        index = self._chain_factor.pop(junction)
        if index is None:
            self._factors = [(owner, factor) for owner, factor in self._factors if owner != junction]
        else:
            self._remove.append(index)

    def _poses_of(self, keys: np.ndarray) -> np.ndarray:
        """The estimates of these experiences (K, 3): a junction's is the solver's; an inner
        experience's where its chain puts it between its two junctions (`_place`); an
        experience of the open chain is its upper junction's composed with the odometry."""
        bottom = self._bottom[keys]
        junction, loose = bottom == keys, bottom < 0
        inner = ~junction & ~loose
        chains = np.unique(bottom[inner])
        needed = [keys[junction], chains, self._top[chains]] + ([np.array([self._open[0]])] if loose.any() else [])
        junctions = np.unique(np.concatenate(needed))
        estimate = self._junction_poses(junctions)
        poses = np.empty((len(keys), 3))
        poses[junction] = estimate[np.searchsorted(junctions, keys[junction])]
        if inner.any():
            nodes, placed = self._place(chains, estimate[np.searchsorted(junctions, self._top[chains])],
                                        estimate[np.searchsorted(junctions, chains)])
            poses[inner] = placed[np.searchsorted(nodes, keys[inner])]
        if loose.any():
            poses[loose] = _compose(estimate[np.searchsorted(junctions, [self._open[0]])], self._in_frame[keys[loose]])
        return poses

    def _place(self, chains: np.ndarray, tops: np.ndarray, bottoms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inner experiences of these chains (given by their lower junctions, ascending) and
        their poses given the poses of both junctions (`_solution`)."""
        nodes, pose, _, _ = self._solution(chains, _between(tops, bottoms))
        chain_of = np.searchsorted(chains, self._bottom[nodes])
        pose = _compose(tops[chain_of], pose)
        inner = nodes != chains[chain_of]
        return nodes[inner], pose[inner]

    def _solution(self, chains: np.ndarray, relative: np.ndarray):
        """The least squares of these chains (lower junctions, ascending) with their junctions at
        `relative` to each other: the odometry's noises ε_k of least Σ ε_kᵀ Σ_k⁻¹ ε_k that make the
        links z_k ∘ Exp(ε_k) lead from one junction to the other, by Gauss–Newton from ε = 0: with
        A_k = Ad(d_k) (d_k: experience k in the chain end's frame) and m the misfit left at the
        end, ε_k = Σ_k A_kᵀ S⁻¹ b, b = m + Σ A_i ε_i, S = Σ A_k Σ_k A_kᵀ. The first step is the
        conditional mean of the linearised chain; the others take up its curvature (the turns the
        misfit's heading makes along a long chain). All chains at once: their experiences (the
        junction last), each one's pose in its upper junction's frame, and each chain's S and b."""
        first = self._first[chains]
        lengths = chains - first + 1
        chain_of = np.repeat(np.arange(len(chains)), lengths)
        starts = np.cumsum(lengths) - lengths
        nodes = first[chain_of] + np.arange(len(chain_of)) - starts[chain_of]
        steps, covariance = self._step[nodes], self._step_covariance[nodes]
        # The first step from the chain at its odometry, as _set_chain linearised it.
        accumulated, carry = self._chain_covariance[chains], self._carry[nodes]
        misfit = _logmap(_between(self._composed[chains], relative))
        multiplier = np.linalg.solve(accumulated, misfit[..., None])
        noise = (covariance @ (carry.transpose(0, 2, 1) @ multiplier[chain_of]))[..., 0]
        for _ in range(PLACEMENT_ITERATIONS - 1):
            pose = _segment_chain_poses(_compose(steps, _expmap(noise)), chain_of, starts)
            end = pose[starts + lengths - 1]
            carry = _adjoint(_between(end[chain_of], pose))
            accumulated = np.add.reduceat(carry @ covariance @ carry.transpose(0, 2, 1), starts, axis=0)
            misfit = _logmap(_between(end, relative)) + np.add.reduceat((carry @ noise[..., None])[..., 0], starts, axis=0)
            multiplier = np.linalg.solve(accumulated, misfit[..., None])
            noise = (covariance @ (carry.transpose(0, 2, 1) @ multiplier[chain_of]))[..., 0]
        return nodes, _segment_chain_poses(_compose(steps, _expmap(noise)), chain_of, starts), accumulated, misfit

    def _junction_poses(self, keys: np.ndarray) -> np.ndarray:
        """The solver's estimates of these junctions (sorted keys), pending ones at their value."""
        poses = np.empty((len(keys), 3))
        if len(keys) > BULK_ESTIMATE:
            values = self.isam.calculateEstimate()
            solved = np.array(values.keys(), dtype=np.int64)
            rows = np.searchsorted(solved, keys)
            found = (rows < len(solved)) & (solved[np.minimum(rows, len(solved) - 1)] == keys) if len(solved) \
                else np.zeros(len(keys), dtype=bool)
            poses[found] = self.gtsam.utilities.extractPose2(values)[rows[found]]
            missing = np.flatnonzero(~found)
        else:
            missing = range(len(keys))
        for i in missing:
            key = int(keys[i])
            pose = self._values.atPose2(key) if self._values.exists(key) else self.isam.calculateEstimatePose2(key)
            poses[i] = pose.x(), pose.y(), pose.theta()
        return poses

    # --- rebuilding -------------------------------------------------------------------------------
    def state(self) -> dict[str, np.ndarray]:
        """The solver's part of the map's state: its junctions and their linearisation point, the
        parts' priors (the first's, `prior`; the later parts', `part_priors`: key, pose, std dev),
        the links' covariances, the refresh plan."""
        junctions = np.array(self._junctions, dtype=np.int64)
        solved = self.isam.calculateEstimate()
        keys = np.array(solved.keys(), dtype=np.int64)
        theta = np.zeros((len(junctions), 3))
        if len(keys):
            theta[np.searchsorted(junctions, keys)] = self.gtsam.utilities.extractPose2(solved)
        pending = [int(key) for key in self._values.keys()]
        for key in pending:
            pose = self._values.atPose2(key)
            theta[np.searchsorted(junctions, key)] = pose.x(), pose.y(), pose.theta()
        priors = np.array([(key, *pose, sigma) for key, (pose, sigma) in sorted(self._priors.items())],
                          dtype=float).reshape(-1, 5)
        return {"junctions": junctions, "theta": theta, "chain_linearized": self._linearized[junctions],
                "prior": priors[0, 1:4], "part_priors": priors[1:],
                "covariances": np.array(self.covariances, dtype=float).reshape(-1, 3, 3),
                "refresh": np.array(sorted(self._refresh.union(pending)), dtype=np.int64),   # the next update would mark them
                "refresh_cursor": np.array(self._cursor, dtype=np.int64)}

    def move_part(self, state: dict[str, np.ndarray], members: np.ndarray, anchor: int,
                  transform: tuple[float, float, float], sigma: float) -> None:
        """In `state` (as `state` gave it, for `rebuild`): the junctions among `members` moved by
        `transform`, and the prior of their part's first experience (`anchor`) with them, its
        standard deviation now `sigma`."""
        for row in np.flatnonzero(np.isin(state["junctions"], members)).tolist():
            state["theta"][row] = compose(transform, tuple(state["theta"][row]))
        for row in state["part_priors"]:
            if int(row[0]) == anchor:
                row[1:4] = compose(transform, tuple(row[1:4]))
                row[4] = sigma

    def rebuild(self, state: dict[str, np.ndarray]) -> None:
        """A fresh iSAM2 holding the graph `state` and the map's links describe, given to it in
        REBUILD_PARTS updates, oldest experiences first. (In one update it would order the whole
        graph anew, and on a map that loops the updates after it re-eliminate far more: the 200
        frames after 8000 of the looping stack's journal took 61 ms a frame instead of 11. In
        parts, recent experiences stay near the root of the Bayes tree, as the live updates
        keep them.) The chains are made again from the links, as they were made live."""
        junctions, theta = np.asarray(state["junctions"], dtype=np.int64), np.asarray(state["theta"], dtype=float)
        covariances = np.asarray(state["covariances"], dtype=float)
        count = len(self.map)
        links = np.asarray(state["links"], dtype=np.int64).reshape(-1, 5)
        if len(theta) != len(junctions) or len(covariances) != len(self.map.links) or len(links) != len(covariances) or \
                (count and (not len(junctions) or junctions[0] != 0 or (np.diff(junctions) <= 0).any()
                            or junctions[-1] >= count)):
            raise ValueError("solver state of another map")
        self._clear(max(64, count))
        self._priors = {0: (tuple(float(v) for v in state["prior"]), PRIOR_SIGMA)}
        for key, x, y, heading, sigma in state.get("part_priors", np.zeros((0, 5))):
            self._priors[int(key)] = ((float(x), float(y), float(heading)), float(sigma))
        self.covariances = list(covariances)
        odometric = links[:, 3] == 0
        targets = links[odometric, 1]
        self._parent[targets] = links[odometric, 0]
        self._step[targets] = np.asarray(state["link_transforms"], dtype=float).reshape(-1, 3)[odometric]
        self._step_covariance[targets] = covariances[odometric]
        self._junctions = junctions.tolist()
        self._bottom[junctions] = junctions
        junction = self._bottom[:count] >= 0
        # A chain's first experience is made from a junction; the others each from the one before.
        # A part's first experience is made from none: a junction, with its prior.
        inner = np.flatnonzero(~junction)
        parents = self._parent[inner]
        first_of_part = self._parent[junctions] < 0
        linearized = np.asarray(state["chain_linearized"], dtype=float).reshape(-1, 3)
        bent = ~np.isnan(linearized[:, 0]) if len(linearized) == len(junctions) else None   # relinearised chains
        if (parents < 0).any() or not (junction[parents] | (parents == inner - 1)).all() or bent is None or \
                (bent & first_of_part).any() or (count and set(junctions[first_of_part].tolist()) != set(self._priors)):
            raise ValueError("solver state of another map")
        starts = inner[junction[parents]]
        chains = {}   # junction → its chain's factor
        for key in junctions[~first_of_part].tolist():
            parent = int(self._parent[key])
            first = key if junction[parent] else int(starts[np.searchsorted(starts, parent, side="right") - 1])
            chains[key] = self._set_chain(key, int(self._parent[first]), first)
        if bent.any():
            chains.update(zip(junctions[bent].tolist(), self._chain_factors_at(junctions[bent], linearized[bent])))
        if count and not junction[count - 1]:
            first = int(starts[np.searchsorted(starts, count - 1, side="right") - 1])
            self._open = (int(self._parent[first]), first)
            self._in_frame[first:count] = _chain_poses(self._step[first:count])
            self._tip = tuple(float(v) for v in self._in_frame[count - 1])
        # (newest experience it links, the junction whose chain it is or -1, factor)
        factors = [(key, -1, self._prior_factor(key)) for key in sorted(self._priors)] if count else []
        factors += [(key, key, factor) for key, factor in chains.items()]
        for link, covariance in zip(self.map.links, self.covariances):
            if link.loop_closure and link.accepted:
                if not (self._bottom[link.source] == link.source and self._bottom[link.target] == link.target):
                    raise ValueError("solver state of another map")
                factors.append((max(link.source, link.target), -1, self._closure_factor(link, covariance)))
        factors.sort(key=lambda item: item[0])
        size, added, position = -(-count // REBUILD_PARTS) if count else 1, 0, 0
        for start in range(0, count, size):
            graph, values, owners = self.gtsam.NonlinearFactorGraph(), self.gtsam.Values(), []
            while position < len(junctions) and junctions[position] < start + size:
                values.insert(int(junctions[position]), self.gtsam.Pose2(*theta[position]))
                position += 1
            while added < len(factors) and factors[added][0] < start + size:
                graph.add(factors[added][2])
                owners.append(factors[added][1])
                added += 1
            if graph.size() or values.size():
                for owner, index in zip(owners, self.isam.update(graph, values).getNewFactorsIndices()):
                    if owner >= 0:
                        self._chain_factor[owner] = index
        self._refresh = {int(key) for key in state["refresh"]}
        self._cursor = int(state["refresh_cursor"])

    def _update(self, remove: list[int] | None = None):
        graph = self.gtsam.NonlinearFactorGraph()
        for _, factor in self._factors:
            graph.add(factor)
        result = self.isam.update(graph, self._values, self._remove + (remove or []))
        for (owner, _), index in zip(self._factors, result.getNewFactorsIndices()):
            if owner >= 0:
                self._chain_factor[owner] = index
        self._factors, self._values, self._remove = [], self.gtsam.Values(), []
        self._refresh.update(result.getMarkedKeys())
        self.updates += 1
        return result

    # --- results ----------------------------------------------------------------------------------
    def solve(self, closure_frame: bool) -> list[int]:
        """Refresh the published poses after a closure frame's solve: the chains at the junctions
        the solver touched plus the next REFRESH_PER_SOLVE experiences; the experiences that
        moved. Other frames solve nothing."""
        count = len(self.map)
        if not closure_frame or not count:
            return []
        window = np.arange(self._cursor, self._cursor + min(REFRESH_PER_SOLVE, count)) % count
        self._cursor = (self._cursor + REFRESH_PER_SOLVE) % count
        # The current experience too: the experiences made until the next solve are composed from it.
        keys = np.unique(np.concatenate([self._chains_at(self._refresh), window, [self.map.current]]))
        self._refresh.clear()
        estimates = self._poses_of(keys)
        moved = keys[(np.abs(self.map.poses[keys] - estimates) > MOVED).any(axis=1)]
        self.map.place(keys, estimates)
        return moved.tolist()

    def _chains_of(self, junctions) -> np.ndarray:
        """The chains (by their lower junctions, ascending) that end at these junctions or start
        at them."""
        marked = np.fromiter(junctions, dtype=np.int64)
        every = np.array(self._junctions, dtype=np.int64)
        every = every[self._top[every] >= 0]   # not the parts' first experiences: no chain ends there
        return every[np.isin(every, marked) | np.isin(self._top[every], marked)]

    def _chains_at(self, junctions) -> np.ndarray:
        """The experiences whose estimates follow these junctions': each, its chain and the chains
        that start at it."""
        chains = self._chains_of(junctions)
        first = self._first[chains]
        lengths = chains - first + 1
        pieces = [np.fromiter(junctions, dtype=np.int64),
                  np.repeat(first - np.cumsum(lengths) + lengths, lengths) + np.arange(lengths.sum())]
        if self._open is not None and self._open[0] in junctions:
            pieces.append(np.arange(self._open[1], len(self.map)))
        return np.concatenate(pieces)

    def estimate(self) -> np.ndarray:
        if self._factors or self._values.size() or self._remove:
            self._update()
        if len(self.map) == 0:
            return np.zeros((0, 3))
        return self._poses_of(np.arange(len(self.map)))


# --- planar poses as arrays (n, 3) for the chains: gtsam's Pose2 conventions, vectorised ---------
def _poses(x, y, heading) -> np.ndarray:
    result = np.empty((len(x), 3))
    result[:, 0], result[:, 1], result[:, 2] = x, y, heading
    return result


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a ∘ b (either may be one pose, (1, 3))."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    x = a[:, 0] + c * b[:, 0] - s * b[:, 1]
    return _poses(x, a[:, 1] + s * b[:, 0] + c * b[:, 1], wrap(a[:, 2] + b[:, 2]))


def _between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a⁻¹ ∘ b (either may be one pose, (1, 3))."""
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return _poses(c * dx + s * dy, -s * dx + c * dy, wrap(b[:, 2] - a[:, 2]))


def _adjoint(pose: np.ndarray) -> np.ndarray:
    """geometry.adjoint of each pose: pose ∘ Exp(ε) = Exp(Ad ε) ∘ pose."""
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    result = np.zeros((len(pose), 3, 3))
    result[:, 0, 0], result[:, 0, 1], result[:, 0, 2] = c, -s, pose[:, 1]
    result[:, 1, 0], result[:, 1, 1], result[:, 1, 2] = s, c, -pose[:, 0]
    result[:, 2, 2] = 1.0
    return result


def _expmap(xi: np.ndarray) -> np.ndarray:
    """SE(2)'s exponential (gtsam's Pose2.Expmap) of tangent vectors (vx, vy, ω)."""
    w = xi[:, 2]
    small = np.abs(w) < 1e-10
    inverse = 1.0 / np.where(small, 1.0, w)
    c, s = np.cos(w), np.sin(w)
    x = np.where(small, xi[:, 0], (s * xi[:, 0] - (1 - c) * xi[:, 1]) * inverse)
    y = np.where(small, xi[:, 1], ((1 - c) * xi[:, 0] + s * xi[:, 1]) * inverse)
    return _poses(x, y, wrap(w))


def _logmap(pose: np.ndarray) -> np.ndarray:
    """SE(2)'s logarithm (gtsam's Pose2.Logmap), the inverse of _expmap: R_π/2 (Rᵀt − t) w / |R − I|²."""
    w, x, y = pose[:, 2], pose[:, 0], pose[:, 1]
    small = np.abs(w) < 1e-10
    c, s = np.cos(w), np.sin(w)
    scale = np.where(small, 1.0, w / np.where(small, 1.0, (c - 1.0) ** 2 + s * s))
    ux, uy = c * x + s * y - x, -s * x + c * y - y
    return _poses(np.where(small, x, -uy * scale), np.where(small, y, ux * scale), w)


def _segment_chain_poses(steps: np.ndarray, chain_of: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """_chain_poses of several chains laid end to end (chain_of: each step's chain; starts: each
    chain's first step): c_k = R(−H_s) Σ_{s≤i≤k} R(H_{i−1}) t_i, H the headings summed over all."""
    heading = np.cumsum(steps[:, 2])
    before = np.empty_like(heading)
    before[0], before[1:] = 0.0, heading[:-1]
    c, s = np.cos(before), np.sin(before)
    x, y = np.cumsum(c * steps[:, 0] - s * steps[:, 1]), np.cumsum(s * steps[:, 0] + c * steps[:, 1])
    origin = starts[chain_of]
    x0, y0 = x[origin] - (c * steps[:, 0] - s * steps[:, 1])[origin], y[origin] - (s * steps[:, 0] + c * steps[:, 1])[origin]
    h0 = before[origin]
    c0, s0 = np.cos(h0), np.sin(h0)
    dx, dy = x - x0, y - y0
    return _poses(c0 * dx + s0 * dy, -s0 * dx + c0 * dy, wrap(heading - h0))


def _chain_poses(steps: np.ndarray) -> np.ndarray:
    """The poses a chain of odometric steps (L, 3) reaches, in its start's frame: c_k = z_1 ∘ … ∘ z_k."""
    heading = np.cumsum(steps[:, 2])
    before = np.concatenate([[0.0], heading[:-1]])
    c, s = np.cos(before), np.sin(before)
    return np.column_stack([np.cumsum(c * steps[:, 0] - s * steps[:, 1]), np.cumsum(s * steps[:, 0] + c * steps[:, 1]),
                            np.where(np.abs(heading) > np.pi, wrap(heading), heading)])


class Relaxation:
    def __init__(self, experience_map: PlacedMap):
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

    def move_part(self, state: dict[str, np.ndarray], members: np.ndarray, anchor: int,
                  transform: tuple[float, float, float], sigma: float) -> None:
        pass   # the map's poses are all it places

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
        poses = self.map.poses.copy()
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
        self.map.place(np.arange(len(poses)), poses)

    def estimate(self) -> np.ndarray:
        return self.map.poses.copy()
