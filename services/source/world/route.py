"""A synthetic world's route: an arc-length parametrised centre line of (length, curvature)
pieces. The corridor world's is a rectangle with rounded corners (radius half the corridor
width), counter-clockwise, starting mid-way along the south side heading east; the campus
builds its own from its tour (campus.py)."""

from __future__ import annotations

import bisect
import math

import numpy as np


class Route:
    """Arc-length parametrised centre line; ``at(s)`` gives position, heading and curvature.
    ``Route(half_x, half_y, radius)`` is the corridor world's; ``Route.from_pieces`` any other."""

    def __init__(self, half_x: float, half_y: float, radius: float):
        a, b, r = half_x, half_y, radius
        # (length, curvature) pieces; positions integrate from (0, -b) heading east.
        pieces = [
            (a - r, 0.0),
            (math.pi * r / 2, 1 / r),
            (2 * (b - r), 0.0),
            (math.pi * r / 2, 1 / r),
            (2 * (a - r), 0.0),
            (math.pi * r / 2, 1 / r),
            (2 * (b - r), 0.0),
            (math.pi * r / 2, 1 / r),
            (a - r, 0.0),
        ]
        self._integrate(pieces, (0.0, -b, 0.0))

    @classmethod
    def from_pieces(cls, pieces: list[tuple[float, float]], start: tuple[float, float, float]) -> Route:
        """A route of (length, curvature) pieces from the pose ``start`` (x, y, heading)."""
        route = cls.__new__(cls)
        route._integrate(list(pieces), start)
        return route

    def _integrate(self, pieces: list[tuple[float, float]], start: tuple[float, float, float]) -> None:
        self.pieces = pieces
        self.starts = []  # (s0, x0, y0, heading0) of each piece
        s, (x, y, h) = 0.0, start
        for length, k in self.pieces:
            self.starts.append((s, x, y, h))
            x, y, h = self._advance(x, y, h, k, length)
            s += length
        self.length = s
        self._ends = [s0 + length for (s0, _, _, _), (length, _) in zip(self.starts, self.pieces)]
        # Heading gained per lap, a whole number of turns for a closed route.
        self.lap_turn = 2 * math.pi * round(sum(length * k for length, k in self.pieces) / (2 * math.pi))

    @staticmethod
    def _advance(x: float, y: float, h: float, k: float, d: float) -> tuple[float, float, float]:
        if k == 0:
            return x + d * math.cos(h), y + d * math.sin(h), h
        h1 = h + k * d
        return x + (math.sin(h1) - math.sin(h)) / k, y - (math.cos(h1) - math.cos(h)) / k, h1

    def curvatures(self, s: np.ndarray) -> np.ndarray:
        """Curvature at every arc length of ``s`` (within one lap)."""
        piece = np.minimum(np.searchsorted(self._ends, s), len(self.pieces) - 1)
        return np.array([k for _, k in self.pieces])[piece]

    def at(self, s: float) -> tuple[float, float, float, float]:
        """(x, y, heading, curvature) at arc length ``s`` (taken modulo the route length)."""
        s = s % self.length
        index = bisect.bisect_left(self._ends, s)  # the first piece that ends at or after s
        if index == len(self.pieces):
            raise AssertionError("unreachable: s is within the route")
        (s0, x0, y0, h0), (_, k) = self.starts[index], self.pieces[index]
        x, y, h = self._advance(x0, y0, h0, k, s - s0)
        return x, y, h, k
