"""Routes on the experience map (RatSLAM's path planning on the experience graph), a pure core:
the shortest path over experiences and links between the experiences nearest two points, each
link costing its length (the distance its transform spans: what the robot drove, or a closure's
measured offset). Links a map refused are no way through; every other link can be driven both
ways. Dijkstra's algorithm with a binary heap."""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from services.expmap.links import Link


@dataclass(frozen=True)
class Route:
    experiences: list[int]          # start to goal
    poses: np.ndarray               # (N, 3) x, y, heading of them
    length: float                   # metres over the links
    found: bool                     # False: no link path joins the two experiences


def nearest(poses: np.ndarray, point: tuple[float, float]) -> int:
    """The experience nearest a point of the map frame."""
    return int(np.argmin(np.hypot(poses[:, 0] - point[0], poses[:, 1] - point[1])))


def shortest_route(poses: np.ndarray, links: list[Link], start: tuple[float, float], goal: tuple[float, float]) -> Route:
    """The shortest route between the experiences nearest ``start`` and ``goal`` (map frame, m)."""
    poses = np.asarray(poses, dtype=float)
    if len(poses) == 0:
        return Route([], np.zeros((0, 3)), 0.0, False)
    source, target = nearest(poses, start), nearest(poses, goal)
    neighbours: dict[int, list[tuple[int, float]]] = {}
    for link in links:
        if link.accepted and link.source != link.target:
            cost = math.hypot(link.dx, link.dy)
            neighbours.setdefault(link.source, []).append((link.target, cost))
            neighbours.setdefault(link.target, []).append((link.source, cost))
    distance = {source: 0.0}
    previous: dict[int, int] = {}
    queue = [(0.0, source)]
    while queue:
        cost, node = heapq.heappop(queue)
        if node == target:
            break
        if cost > distance[node]:
            continue
        for other, step in neighbours.get(node, ()):
            if cost + step < distance.get(other, math.inf):
                distance[other] = cost + step
                previous[other] = node
                heapq.heappush(queue, (cost + step, other))
    if target not in distance:
        return Route([source, target], poses[[source, target]], 0.0, False)
    path = [target]
    while path[-1] != source:
        path.append(previous[path[-1]])
    path.reverse()
    return Route(path, poses[path], float(distance[target]), True)
