"""Geometry, once: angles, SE(2) poses (x, y, heading) and their algebra; the SE(3) camera
transforms (4×4) and the planar increments they make.

Conventions: the plane is x forward/east, y left/north, heading counter-clockwise from x, in
radians; angles are wrapped to [-π, π). A pose's `compose(pose, offset)` is pose ∘ offset,
`between(a, b)` the offset of b in a's frame (a ∘ between(a, b) = b). A camera frame is x right,
y down, z forward; a camera transform T maps a point's coordinates in the previous camera frame
to the current one, p_cur = T p_prev (LIBVISO2's `Tr`, what cv2.solvePnP and cv2.recoverPose
return); the camera's own motion is inv(T) (docs/egomotion.md)."""

from __future__ import annotations

import math

import cv2
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


def increment_from_transform(transform: np.ndarray) -> tuple[float, float, float]:
    """(forward, left, yaw) of the camera motion described by ``transform`` (p_cur = T p_prev).

    The camera's pose in the previous frame is M = inv(T); forward is its z translation, left
    its −x translation, yaw the heading of its optical axis about the up axis (−y):
    atan2(−M13, M33), which is the data README's asin(−Tt13) for level motion.
    """
    return planar_from_camera(invert_transform(transform))


def transform_from_increment(forward: float, left: float, yaw: float) -> np.ndarray:
    """The camera transform (p_cur = T p_prev) of a level planar motion; inverse of
    `increment_from_transform` for motions without pitch, roll or height change."""
    c, s = math.cos(yaw), math.sin(yaw)
    motion = np.eye(4)
    # Counter-clockwise yaw turns the optical axis (z) toward −x (left): a rotation about −y.
    motion[:3, :3] = [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]
    motion[:3, 3] = [-left, 0.0, forward]
    return invert_transform(motion)


def invert_transform(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4×4 transform (rotation transposed), exact and cheap."""
    inverse = np.eye(4)
    rotation = transform[:3, :3]
    inverse[:3, :3] = rotation.T
    inverse[:3, 3] = -rotation.T @ transform[:3, 3]
    return inverse


def transform_from_rt(rvec_or_matrix: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """A 4×4 from an OpenCV rotation (Rodrigues vector or 3×3 matrix) and translation."""
    rotation = np.asarray(rvec_or_matrix, dtype=float)
    if rotation.shape != (3, 3):
        rotation = cv2.Rodrigues(rotation.reshape(3, 1))[0]
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = np.asarray(tvec, dtype=float).reshape(3)
    return transform
