"""The revisits of a synthetic world's route, from its exact poses, and the passes of its
look-alike places: what a place recognition should find, and what it must not take for a
revisit."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from services.source.world.layout import in_region

if TYPE_CHECKING:
    from services.source.synthetic import SyntheticWorld


@dataclass(frozen=True)
class Revisit:
    """A stretch of the route that passes a place seen before: frames ``frames[0]``…``frames[1]``
    (inclusive) of the later pass, matched to the earlier pass's ``earlier[0]``…``earlier[1]``."""

    frames: tuple[int, int]
    earlier: tuple[int, int]
    length: float  # metres driven over the later pass's frames
    direction: str  # "same" or "opposite": the later pass's heading against the earlier one's
    lookalike: bool  # True: not the same place but its look-alike (campus.Twin)
    distance: float  # median distance (m) between the matched places: the sway for a revisit, the offset for a look-alike


def revisits(world: SyntheticWorld, radius: float = 1.0, separation: float = 30.0, min_length: float = 2.0) -> list[Revisit]:
    """The revisits of a world's route, from its exact poses, and the passes of look-alike places.

    Frame i revisits frame j < i when they stand within ``radius`` metres, more than
    ``separation`` metres of route apart, heading within 45° of each other (same direction)
    or of the opposite. For each direction on its own, each frame takes the most recent such j
    (and the nearest frame of that pass); runs of consecutive frames whose matched frames
    advance steadily form a Revisit (``min_length`` metres or more). So a stretch driven
    before both ways appears twice, once per direction. A look-alike pass is found the same
    way between a twin region's frames shifted by its offset and its original's frames, in
    whichever order they were driven."""
    poses = world.poses
    count = len(poses)
    along = np.array([world.distance(seq) for seq in range(count)])
    everywhere = np.ones(count, bool)
    found = []
    for direction in ("same", "opposite"):
        found += _revisit_runs(poses, poses[:, :2], along, everywhere, everywhere, radius, separation, direction, False)
        for twin in world.layout.twins if world.layout is not None else ():
            inside = in_region(poses[:, :2], twin.region)
            moved = in_region(poses[:, :2], twin.moved())
            mapped = poses[:, :2] - np.where(moved[:, None], np.asarray(twin.offset), 0.0)
            found += _revisit_runs(poses, mapped, along, inside, moved, radius, 0.0, direction, True)
            found += _revisit_runs(poses, mapped, along, moved, inside, radius, 0.0, direction, True)
    return sorted((r for r in found if r.length >= min_length), key=lambda r: (r.frames, r.lookalike, r.direction))


def _revisit_runs(poses, points, along, earlier_ok, later_ok, radius, separation, direction, lookalike) -> list[Revisit]:
    """Revisits in ``direction`` of frames ``later_ok`` to earlier frames ``earlier_ok``, matched on ``points``."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(points).sparse_distance_matrix(cKDTree(points), radius, output_type="ndarray")
    i, j, gap = pairs["i"], pairs["j"], pairs["v"]
    turn = np.cos(poses[i, 2] - poses[j, 2])
    aligned = (turn if direction == "same" else -turn) >= math.cos(math.radians(45))
    keep = (j < i) & later_ok[i] & earlier_ok[j] & (along[i] - along[j] >= separation) & aligned
    i, j, gap = i[keep], j[keep], gap[keep]
    if not len(i):
        return []
    # Each frame's most recent earlier pass, and in it the nearest frame.
    latest = np.zeros(len(poses), int)
    np.maximum.at(latest, i, j)
    same_pass = along[latest[i]] - along[j] <= 2 * radius
    i, j, gap = i[same_pass], j[same_pass], gap[same_pass]
    order = np.lexsort((gap, i))
    first = order[np.r_[True, np.diff(i[order]) > 0]]
    frames, matched = i[first], j[first]
    runs = np.split(np.arange(len(frames)), np.flatnonzero((np.diff(frames) != 1) | (np.abs(np.diff(matched)) > 10)) + 1)
    return [
        Revisit((int(frames[run[0]]), int(frames[run[-1]])), (int(matched[run[0]]), int(matched[run[-1]])),
                float(along[frames[run[-1]]] - along[frames[run[0]]]), direction, lookalike,
                float(np.median(np.hypot(*(poses[frames[run], :2] - poses[matched[run], :2]).T))))
        for run in runs
    ]
