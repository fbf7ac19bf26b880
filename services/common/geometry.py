"""Planar geometry, once: angles, SE(2) poses (x, y, heading) and their algebra.

Conventions: the plane is x forward/east, y left/north, heading counter-clockwise from x, in
radians; angles are wrapped to [-π, π). A pose's `compose(pose, offset)` is pose ∘ offset,
`between(a, b)` the offset of b in a's frame (a ∘ between(a, b) = b)."""

from __future__ import annotations

import math

import numpy as np

Pose2 = tuple[float, float, float]


def wrap(angle):
    """Angle(s) wrapped to [-π, π) (a scalar or an array of them)."""
    return (np.asarray(angle, dtype=float) + math.pi) % (2.0 * math.pi) - math.pi


def compose(pose: Pose2, offset: Pose2) -> Pose2:
    """pose ∘ offset."""
    x, y, th = pose
    dx, dy, dth = offset
    c, s = math.cos(th), math.sin(th)
    return x + c * dx - s * dy, y + s * dx + c * dy, float(wrap(th + dth))


def between(a: Pose2, b: Pose2) -> Pose2:
    """The offset of b in a's frame: a ∘ between(a, b) = b."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    c, s = math.cos(a[2]), math.sin(a[2])
    return c * dx + s * dy, -s * dx + c * dy, float(wrap(b[2] - a[2]))


def inverse(pose: Pose2) -> Pose2:
    return between(pose, (0.0, 0.0, 0.0))


def adjoint(pose: Pose2) -> np.ndarray:
    """SE(2) adjoint: carries a right-hand tangent perturbation across `pose`
    (pose ∘ Exp(ε) = Exp(Ad ε) ∘ pose); tangent order (x, y, heading)."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    return np.array([[c, -s, y], [s, c, -x], [0.0, 0.0, 1.0]])


def planar_from_camera(matrix: np.ndarray) -> Pose2:
    """The planar pose (x forward, y left, heading counter-clockwise) of a 4×4 pose in the camera
    convention (x right, y down, z forward): forward = z, left = −x, and the heading of the
    optical axis about the up axis (−y), atan2(−R[0,2], R[2,2]) (docs/sources.md, Conventions)."""
    m = np.asarray(matrix, dtype=float)
    return float(m[2, 3]), float(-m[0, 3]), math.atan2(-m[0, 2], m[2, 2])


def planar_motion(before: np.ndarray, after: np.ndarray) -> Pose2:
    """Body-frame motion (forward, left, yaw) between two 4×4 camera poses in the camera convention."""
    return planar_from_camera(np.linalg.inv(before) @ after)
