"""Pairwise consistency of inter-robot closures (Mangelson, Dominic, Eustice & Vasudevan, "Pairwise
Consistency Maximization for Robust Multi-Robot Map Merging", ICRA 2018), a pure core.

Two closures between the same two parts of the fleet map are *consistent* when the loop they
close with each part's own map agrees: from closure c's end in part Y back over c to part X,
along X's map to closure d's start, over d to part Y, and along Y's map back to c's end, the
poses must compose to the identity within `gate` standard deviations, the two closures' covariances
and each part's uncertainty between the two places (a drift that grows with the distance
between them) included. The closures that can join two parts are a largest set of mutually
consistent ones: the maximum clique of the consistency graph, found exactly (Bron–Kerbosch with
pivoting) over at most a bounded number of candidates. A set of look-alike closures is consistent
among itself too (they all put the second robot at the copy's original), which is why the fleet
map asks more of a set than its size (graph.py: its span, and no rival set as large).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.common.geometry import adjoint, between, compose, inverse
from services.common.settings import check, setting


@dataclass(frozen=True)
class ConsistencyParams:
    LABEL = "fleet map consistency"

    gate: float = setting(3.0, gt=0, help="Largest loop error, standard deviations, for two closures to be consistent.")
    translation_drift: float = setting(0.02, ge=0, help="A part's position uncertainty per metre between two places, m/m.")
    heading_drift: float = setting(0.002, ge=0, help="A part's heading uncertainty per metre between two places, rad/m.")
    translation_floor: float = setting(0.1, gt=0, help="A part's position uncertainty between any two places, m.")
    heading_floor: float = setting(0.02, gt=0, help="A part's heading uncertainty between any two places, rad.")

    def check(self) -> None:
        check(self)


@dataclass(frozen=True)
class Candidate:
    """A closure as the consistency test sees it: the link `source → target` (source in part X,
    target in part Y) with its covariance, and the two experiences' poses in their own parts."""

    key: int
    source: tuple[float, float, float]
    target: tuple[float, float, float]
    link: tuple[float, float, float]
    covariance: np.ndarray


def drift(params: ConsistencyParams, distance: float) -> np.ndarray:
    t = params.translation_floor + params.translation_drift * distance
    h = params.heading_floor + params.heading_drift * distance
    return np.diag([t * t, t * t, h * h])


def loop_error(c: Candidate, d: Candidate, params: ConsistencyParams) -> float:
    """Mahalanobis norm of the loop c, X's map, d, Y's map (module docstring)."""
    across = between(c.source, d.source)                      # in X, from c's source to d's
    via = compose(compose(inverse(c.link), across), d.link)   # c's target to d's target, through X
    direct = between(c.target, d.target)                      # the same, in Y
    error = np.array(between(via, direct))
    # c's link error enters at the loop's start (carried across it), d's at its end, X's drift
    # before d's link, Y's at the end (the error is near the identity when consistent).
    carry_c = adjoint(inverse(via))
    carry_x = adjoint(inverse(d.link))
    covariance = (carry_c @ c.covariance @ carry_c.T + d.covariance
                  + carry_x @ drift(params, math.hypot(*across[:2])) @ carry_x.T
                  + drift(params, math.hypot(*direct[:2])))
    return float(math.sqrt(max(error @ np.linalg.solve(covariance, error), 0.0)))


def consistency_graph(candidates: list[Candidate], params: ConsistencyParams) -> dict[int, set[int]]:
    """Each candidate's key → the keys of the candidates consistent with it."""
    neighbours: dict[int, set[int]] = {c.key: set() for c in candidates}
    for i, c in enumerate(candidates):
        for d in candidates[i + 1:]:
            if loop_error(c, d, params) <= params.gate and loop_error(d, c, params) <= params.gate:
                neighbours[c.key].add(d.key)
                neighbours[d.key].add(c.key)
    return neighbours


def maximum_clique(neighbours: dict[int, set[int]], among: set[int] | None = None) -> list[int]:
    """A largest set of mutually consistent keys (of ``among``, default all), sorted; of several
    as large, the one whose sorted keys come first (deterministic)."""
    best: list[int] = []

    def expand(clique: list[int], candidates: set[int], excluded: set[int]) -> None:
        nonlocal best
        if not candidates and not excluded:
            found = sorted(clique)
            if len(found) > len(best) or (len(found) == len(best) and found < best):
                best = found
            return
        if len(clique) + len(candidates) < len(best):
            return
        pivot = max(sorted(candidates | excluded), key=lambda k: len(neighbours[k] & candidates))
        for key in sorted(candidates - neighbours[pivot]):
            expand(clique + [key], candidates & neighbours[key], excluded & neighbours[key])
            candidates = candidates - {key}
            excluded = excluded | {key}

    keys = set(neighbours) if among is None else set(among)
    expand([], keys, set())
    return best
