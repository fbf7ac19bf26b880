"""Grid-cell path integration (Lu et al., ROBIO 2016): heading from integrated yaw
(head-direction cells), direction of travel from the flow of the grid-cell lattice, step
length from the ego-motion (paper eq. 5).

Per frame, as the authors' code does it: heading += yaw; the body-frame translation is rotated
into the world by the *updated* heading; the world velocity (times ``velocity_scale``, network
units per metre) drives the network for one frame; a decoder reads the lattice shift (dx, dy)
in columns and rows since the previous frame; the pose moves by the ego-motion's step length
|v| along (dx, −dy)/|(dx, dy)| (columns grow with world x, rows shrink with world y). A zero
shift gives no step.

Conventions: body frame x forward, y left, yaw counter-clockwise positive (REP 103); world
frame x, y with heading measured from world +x, wrapped to (−π, π].
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from services.gridcells.decoders import DECODERS
from services.gridcells.network import GridCellError, GridNetwork, NetworkParams

log = logging.getLogger(__name__)

__all__ = [
    "DeadReckoning",
    "GridCellError",
    "GridCellIntegrator",
    "GridStep",
    "Pose2D",
    "auto_velocity_scale",
    "LATTICE_RATE",
    "LINEAR_LIMIT",
]

# Lattice flow per network step per unit of α·|v| (neurons), measured with the default network
# (`tests/unit/test_gridcells_network.py` checks it): 38.3 neurons per frame per network unit
# of velocity at α = 2 and 50 steps per frame.
LATTICE_RATE = 0.383
# The flow is proportional to α·|v| up to about α·|v| = 0.3 (within 3 %: 5.6 neurons per frame
# at the defaults); beyond, its speed saturates (about 8.6 neurons per frame) and its direction
# bends toward the lattice axes. Frames driven beyond this are flagged ``saturated``.
LINEAR_LIMIT = 0.3
# auto_velocity_scale puts the 95th-percentile speed at this shift per frame (neurons): half
# the linear range, a third of the ±9 search, so speeds up to ~1.9× that percentile stay linear.
TARGET_SHIFT = 3.0


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


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


def _finite(**values: float) -> None:
    for name, value in values.items():
        if value is not None and not math.isfinite(value):
            raise GridCellError(f"motion input '{name}' is {value}: expected a finite number")


def _body_to_world(forward: float, left: float, heading: float) -> tuple[float, float]:
    c, s = math.cos(heading), math.sin(heading)
    return forward * c - left * s, forward * s + left * c


class PathIntegrator:
    """What both integrators share: the head-direction integration of yaw (heading += yaw, then
    the body-frame step is rotated into the world by the new heading, as the authors' code does),
    the pose, and the counters. Subclasses turn a world-frame displacement into a step."""

    def __init__(self, heading0: float = 0.0):
        _finite(heading0=heading0)
        self._pose = Pose2D(0.0, 0.0, _wrap(heading0))
        self.frames = 0
        self.saturations = 0

    @property
    def pose(self) -> Pose2D:
        return self._pose

    def step(self, forward: float, left: float, yaw: float) -> GridStep:
        """One frame of body-frame increments (input units and rad per frame)."""
        _finite(forward=forward, left=left, yaw=yaw)
        heading = _wrap(self._pose.heading + yaw)
        vx, vy = _body_to_world(forward, left, heading)
        return self._advance(vx, vy, heading)

    def step_world(self, vx: float, vy: float, heading: float | None = None) -> GridStep:
        """One frame of world-frame displacement (the authors' network input); ``heading``,
        when given, becomes the pose's heading."""
        _finite(vx=vx, vy=vy, heading=heading)
        return self._advance(vx, vy, self._pose.heading if heading is None else _wrap(heading))

    def _advance(self, vx: float, vy: float, heading: float) -> GridStep:
        raise NotImplementedError

    def checkpoint(self) -> dict:
        """What evolves from frame to frame; restore() on a fresh integrator of the same
        parameters resumes exactly."""
        return {"pose": (self._pose.x, self._pose.y, self._pose.heading), "frames": self.frames,
                "saturations": self.saturations}

    def restore(self, checkpoint: dict) -> None:
        self._pose = Pose2D(*(float(v) for v in checkpoint["pose"]))
        self.frames, self.saturations = int(checkpoint["frames"]), int(checkpoint["saturations"])


class GridCellIntegrator(PathIntegrator):
    """The grid-cell odometry. ``decoder`` is "paper", "fft" or "subpixel" (see decoders.py).

    ``paper`` reproduces the authors' code: a float64 network (their doubles), and the first
    frame only stores the pattern. The other decoders use a float32 network and compare the
    first frame with the settled field, so the first frame's motion is not lost.

    ``velocity_scale`` converts input units to network units (see auto_velocity_scale); the
    step length stays in input units. A frame is ``saturated`` when the network is driven
    beyond its linear range (α·|v|·scale > LINEAR_LIMIT) or the decoded shift reaches the
    edge of the search (|dx| or |dy| ≥ search − ½); ``saturations`` counts them and the first
    one is logged as a warning. With velocity_scale = 1 the authors' NuBot input (metres)
    saturates from about 0.15 m per frame on.
    """

    def __init__(
        self,
        params: NetworkParams = NetworkParams(),
        decoder: str = "subpixel",
        velocity_scale: float = 1.0,
        heading0: float = 0.0,
        network: GridNetwork | None = None,
        *,
        search: int = 9,
    ):
        if decoder not in DECODERS:
            raise GridCellError(f"unknown decoder '{decoder}': choose one of {', '.join(DECODERS)}")
        if not (math.isfinite(velocity_scale) and velocity_scale > 0):
            raise GridCellError(f"velocity scale {velocity_scale}: must be a positive number (network units per metre)")
        super().__init__(heading0)
        self.decoder = decoder
        self.velocity_scale = float(velocity_scale)
        self.search = int(search)
        self.network = network or GridNetwork(params, dtype=np.float64 if decoder == "paper" else np.float32)
        self.params = self.network.params
        self._decode = DECODERS[decoder]
        self._previous = None if decoder == "paper" else self.network.field

    @property
    def activity(self) -> np.ndarray:
        """The current rectified field f (n×n copy)."""
        return self.network.field

    def _advance(self, vx: float, vy: float, heading: float) -> GridStep:
        scale = self.velocity_scale
        field = self.network.run((vx * scale, vy * scale))
        self.frames += 1
        previous, self._previous = self._previous, field
        if previous is None:  # the authors' first frame only stores the pattern
            self._pose = Pose2D(self._pose.x, self._pose.y, heading)
            return GridStep(self._pose, (0.0, 0.0), 0.0, False)
        dx, dy = self._decode(previous, field, self.search)
        speed = math.hypot(vx, vy)
        saturated = self.params.alpha * speed * scale > LINEAR_LIMIT or max(abs(dx), abs(dy)) >= self.search - 0.5
        if saturated:
            self.saturations += 1
            level = logging.WARNING if self.saturations == 1 else logging.DEBUG
            log.log(level, "frame %d: lattice flow saturated (network speed α·|v| = %.3g, linear up to %.2g; shift %.2f, %.2f; "
                    "lower the velocity scale)", self.frames, self.params.alpha * speed * scale, LINEAR_LIMIT, dx, dy)
        length = math.hypot(dx, dy)
        x, y, step_length = self._pose.x, self._pose.y, 0.0
        if length > 0:  # eq. 5: step length from the ego-motion, direction from the lattice
            x += speed * dx / length
            y -= speed * dy / length
            step_length = speed
        self._pose = Pose2D(x, y, heading)
        return GridStep(self._pose, (dx, dy), step_length, saturated)

    def checkpoint(self) -> dict:
        """The pose and counters, the network activity and the last field."""
        return {**super().checkpoint(), "state": self.network.state, "previous": self._previous}

    def restore(self, checkpoint: dict) -> None:
        super().restore(checkpoint)
        self.network.state = checkpoint["state"]
        self._previous = checkpoint["previous"]


class DeadReckoning(PathIntegrator):
    """The baseline: the same inputs and heading convention, integrated directly."""

    def _advance(self, vx: float, vy: float, heading: float) -> GridStep:
        self.frames += 1
        self._pose = Pose2D(self._pose.x + vx, self._pose.y + vy, heading)
        return GridStep(self._pose, (0.0, 0.0), math.hypot(vx, vy), False)


def auto_velocity_scale(speeds_m_per_frame, params: NetworkParams = NetworkParams(), target_shift: float = TARGET_SHIFT) -> float:
    """Network units per metre so that the 95th percentile of the observed speeds moves the
    lattice by ``target_shift`` neurons per frame:

        scale = target_shift / (LATTICE_RATE · α · steps_per_frame · p95(|v|))

    The lattice flow is LATTICE_RATE·α·|v| neurons per step while α·|v| ≤ LINEAR_LIMIT, so the
    default target (3 neurons per frame) keeps speeds up to ~1.9× the percentile linear and
    well inside the ±9 search. Examples at the defaults: a rat at 0.1 cm per frame → 78 (its
    input in network units is 0.078 per frame); a car at 1.2 m per frame → 0.065. Returns 1.0
    when every speed is zero (any scale then gives the same result).
    """
    speeds = np.abs(np.asarray(speeds_m_per_frame, dtype=np.float64).ravel())
    if speeds.size == 0:
        raise GridCellError("auto velocity scale: no speeds given")
    if not np.all(np.isfinite(speeds)):
        raise GridCellError(f"auto velocity scale: speed at frame {int(np.flatnonzero(~np.isfinite(speeds))[0])} is not finite")
    if not (math.isfinite(target_shift) and target_shift > 0):
        raise GridCellError(f"auto velocity scale: target shift {target_shift} must be positive")
    moving = speeds[speeds > 0]
    if moving.size == 0:
        return 1.0
    # The percentile of the moving frames: a robot that mostly stands still still needs its
    # moving frames inside the linear range.
    typical = float(np.percentile(moving, 95))
    return target_shift / (LATTICE_RATE * params.alpha * params.steps_per_frame * typical)
