"""Path integration of planar ego-motion increments, shared by the gridcells integrators (whose
baseline DeadReckoning is) and the observers that draw the odometry's path (viewer, Foxglove
bridge): the pose, one step, the head-direction integration of yaw (heading += yaw, then the
body-frame translation is rotated into the world by the new heading, as Lu et al.'s code does),
and `turn_first`, which turns an EgoMotion increment into that order.

Conventions: body frame x forward, y left, yaw counter-clockwise positive (REP 103); world
frame x, y with heading measured from world +x, wrapped to [−π, π)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from services.common.errors import DataError
from services.common.geometry import wrap


class MotionError(DataError):
    """Motion input that cannot be integrated (NaN or infinite)."""


@dataclass(frozen=True)
class Pose2D:
    x: float  # world x, input units (metres)
    y: float  # world y
    heading: float  # rad from world +x, counter-clockwise, in (−π, π]


@dataclass(frozen=True)
class GridStep:
    pose: Pose2D  # pose after this frame
    shift: tuple[float, float]  # decoded lattice shift (dx columns, dy rows) since the last frame
    step_length: float  # distance the pose moved this frame (0 when no step was taken)
    saturated: bool  # the network was driven beyond its linear range or the shift hit the search edge


def body_to_world(forward: float, left: float, heading: float) -> tuple[float, float]:
    c, s = math.cos(heading), math.sin(heading)
    return forward * c - left * s, forward * s + left * c


class PathIntegrator:
    """What both integrators share: the head-direction integration of yaw (heading += yaw, then
    the body-frame step is rotated into the world by the new heading, as the authors' code does),
    the pose, and the counters. Subclasses turn a world-frame displacement into a step; a
    non-finite input raises their `error` (MotionError unless they name another DataError)."""

    error: type[DataError] = MotionError

    def __init__(self, heading0: float = 0.0):
        self._finite(heading0=heading0)
        self._pose = Pose2D(0.0, 0.0, float(wrap(heading0)))
        self.frames = 0
        self.saturations = 0

    @property
    def pose(self) -> Pose2D:
        return self._pose

    def step(self, forward: float, left: float, yaw: float) -> GridStep:
        """One frame of body-frame increments (input units and rad per frame)."""
        self._finite(forward=forward, left=left, yaw=yaw)
        heading = float(wrap(self._pose.heading + yaw))
        vx, vy = body_to_world(forward, left, heading)
        return self._advance(vx, vy, heading)

    def step_world(self, vx: float, vy: float, heading: float | None = None) -> GridStep:
        """One frame of world-frame displacement (the authors' network input); ``heading``,
        when given, becomes the pose's heading."""
        self._finite(vx=vx, vy=vy, heading=heading)
        return self._advance(vx, vy, self._pose.heading if heading is None else float(wrap(heading)))

    def _advance(self, vx: float, vy: float, heading: float) -> GridStep:
        raise NotImplementedError

    def _finite(self, **values: float | None) -> None:
        for name, value in values.items():
            if value is not None and not math.isfinite(value):
                raise self.error(f"motion input '{name}' is {value}: expected a finite number")

    def checkpoint(self) -> dict:
        """What evolves from frame to frame; restore() on a fresh integrator of the same
        parameters resumes exactly."""
        return {"pose": (self._pose.x, self._pose.y, self._pose.heading), "frames": self.frames,
                "saturations": self.saturations}

    def restore(self, checkpoint: dict) -> None:
        self._pose = Pose2D(*(float(v) for v in checkpoint["pose"]))
        self.frames, self.saturations = int(checkpoint["frames"]), int(checkpoint["saturations"])


def turn_first(forward: float, left: float, yaw: float) -> tuple[float, float]:
    """An SE(2) increment (translation in the body frame *before* the frame's yaw, as the
    EgoMotion message and planar_increments define it) in the integrators' order (turn first,
    then move in the new body frame, as the authors' code does): the translation turned by −yaw."""
    c, s = math.cos(yaw), math.sin(yaw)
    return c * forward + s * left, -s * forward + c * left


class DeadReckoning(PathIntegrator):
    """The baseline: the same inputs and heading convention, integrated directly."""

    def _advance(self, vx: float, vy: float, heading: float) -> GridStep:
        self.frames += 1
        self._pose = Pose2D(self._pose.x + vx, self._pose.y + vy, heading)
        return GridStep(self._pose, (0.0, 0.0), math.hypot(vx, vy), False)
