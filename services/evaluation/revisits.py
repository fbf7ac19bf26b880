"""Ground truth of revisits: which earlier frames a frame sees again, and so whether a loop
closure between two frames is true.

Three kinds, one interface (`is_true(frame, matched)`, `revisit_frames`):

- a mask image (`RevisitMask`): N×N, row i and column j white where frame i sees the place of
  the earlier frame j (RTAB-Map's `samples_GT.bmp` layout);
- poses (`RevisitRadius`): frames within `radius` metres of each other are the same place; a
  frame is a revisit when an earlier frame at least `recent` frames before it was within the
  radius looking the same way (within `max_angle_deg`: a forward camera does not recognise a
  place it passes in the other direction, so those passes are no misses);
- frame ranges (`RevisitRanges`, "180-204:0-40"): every frame of the first range revisits every
  frame of the second (NuBot's loop, which has no poses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.common.errors import DataError


TRUE_CLOSURE_M = 2.0   # a closure between frames farther apart than this (by ground truth) is false


class GroundTruthError(DataError):
    """A ground-truth file or spec that cannot be read (the message names it)."""


def same_place(a, b, radius: float = TRUE_CLOSURE_M) -> bool:
    """Whether two true positions (x, y) are one place: a closure between them is true."""
    return math.dist(a, b) <= radius


@dataclass(frozen=True)
class RevisitMask:
    mask: np.ndarray   # (N, N) bool, [frame, earlier frame]

    def is_true(self, frame: int, matched: int) -> bool:
        n = len(self.mask)
        return 0 <= matched < n and 0 <= frame < n and bool(self.mask[frame, matched] or self.mask[matched, frame])

    @property
    def revisit_frames(self) -> set[int]:
        return {int(i) for i in np.flatnonzero(self.mask.any(axis=1))}

    @classmethod
    def read(cls, path: Path) -> RevisitMask:
        import cv2

        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise GroundTruthError(f"{path}: not an image OpenCV can read")
        if image.shape[0] != image.shape[1]:
            raise GroundTruthError(f"{path}: a revisit mask must be square (N×N frames), this is {image.shape[1]}×{image.shape[0]}")
        return cls(image > 127)


@dataclass(frozen=True)
class RevisitRadius:
    positions: np.ndarray   # (N, 2) metres, by frame
    headings: np.ndarray    # (N,) radians
    radius: float
    recent: int = 30
    max_angle_deg: float = 90.0

    def is_true(self, frame: int, matched: int) -> bool:
        n = len(self.positions)
        return 0 <= frame < n and 0 <= matched < n and same_place(self.positions[frame], self.positions[matched], self.radius)

    @property
    def revisit_frames(self) -> set[int]:
        found = set()
        limit = math.radians(self.max_angle_deg)
        for i in range(self.recent, len(self.positions)):
            earlier = self.positions[:i - self.recent + 1]
            near = np.hypot(*(earlier - self.positions[i]).T) <= self.radius
            turn = np.abs(np.remainder(self.headings[:len(earlier)] - self.headings[i] + math.pi, 2 * math.pi) - math.pi)
            if np.any(near & (turn <= limit)):
                found.add(i)
        return found


@dataclass(frozen=True)
class RevisitRanges:
    ranges: tuple[tuple[range, range], ...]   # (revisiting frames, revisited frames)

    def is_true(self, frame: int, matched: int) -> bool:
        return any((frame in later and matched in earlier) or (matched in later and frame in earlier)
                   for later, earlier in self.ranges)

    @property
    def revisit_frames(self) -> set[int]:
        return {frame for later, _ in self.ranges for frame in later}

    @classmethod
    def parse(cls, text: str) -> RevisitRanges:
        """"A-B:C-D[,E-F:G-H]": frames A..B revisit frames C..D (inclusive)."""
        pairs = []
        for part in text.split(","):
            try:
                later, earlier = (_frames(side) for side in part.split(":"))
            except ValueError:
                raise GroundTruthError(f"revisit ranges {text!r}: expected FIRST-LAST:FIRST-LAST, e.g. 180-204:0-40") from None
            pairs.append((later, earlier))
        return cls(tuple(pairs))


def _frames(text: str) -> range:
    first, dash, last = text.strip().partition("-")
    if not dash:
        raise ValueError(text)
    return range(int(first), int(last) + 1)


def from_poses(positions: np.ndarray, headings: np.ndarray, radius: float, recent: int = 30) -> RevisitRadius:
    if not radius > 0:
        raise GroundTruthError(f"the same-place radius must be positive, got {radius}")
    return RevisitRadius(np.asarray(positions, float)[:, :2], np.asarray(headings, float), radius, recent)


def read_ground_truth(spec: str, radius: float | None = None, recent: int = 30):
    """A ground truth from a mask image, a TUM or KITTI poses file (with ``radius``) or frame
    ranges ("180-204:0-40")."""
    path = Path(spec)
    if not path.exists():
        if ":" in spec and "-" in spec:
            return RevisitRanges.parse(spec)
        raise GroundTruthError(f"{spec}: no such ground-truth file (a mask image, a poses file, or ranges A-B:C-D)")
    if path.suffix.lower() in (".png", ".bmp", ".pgm", ".tif", ".tiff", ".jpg"):
        return RevisitMask.read(path)
    from services.evaluation.trajectory import camera_to_planar, read_kitti, read_tum

    if radius is None:
        raise GroundTruthError(f"{path}: a poses file needs --radius M (the distance within which frames are one place)")
    try:
        trajectory = read_tum(path)
    except DataError:
        trajectory = camera_to_planar(read_kitti(path))
    x, y, heading = trajectory.planar()
    return from_poses(np.column_stack((x, y)), heading, radius, recent)
