"""The experience map's plain types, shared by the map (graph.py), its optimisers
(optimizers.py) and a localisation on it (localizer.py): a link between two experiences, a
confirmed loop closure as the map takes it, and what counts as an experience having moved."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

METHODS = ("stereo", "mono", "scanline")   # how a closure's relative pose was measured
MOVED = np.array([1e-3, 1e-3, 1e-4])       # what counts as moved: 1 mm, 0.1 mrad


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
