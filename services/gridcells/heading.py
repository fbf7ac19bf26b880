"""A head-direction ring attractor (issue 13, `--heading ring`): the heading is the position
of a bump of activity on a ring of head-direction cells, moved by the angular velocity.

The model is the classic threshold-linear ring (Ben-Yishai, Bar-Or & Sompolinsky 1995;
Hansel & Sompolinsky 1998) with the rotation mechanism of Skaggs et al. (1995) and Zhang
(1996): N cells with preferred directions θ_i = 2πi/N,

    τ dh_i/dt = −h_i + (1/N) Σ_j W(θ_i − θ_j − δ)·[h_j]₊ + I₀,   W(θ) = J₀ + J₁·cos θ,

where δ = 0 holds a stationary bump (J₁ > 2: the uniform state is unstable, J₀ < 0: the bump's
amplitude is bounded) and δ ≠ 0 tilts the connections toward one side (Zhang's W + γ·W′ to
first order), so the bump turns at a rate set by δ. The cosine kernel makes the recurrent input
depend only on the first two Fourier moments of the rates, so a step costs O(N).

The rate of turn for a given δ is measured once per parameter set (`RingCalibration`) and
inverted, so a yaw increment ψ per frame is given the δ that turns the bump by ψ. The heading
is read as the population vector of the rates. Limits (docs/gridcells.md): a yaw per frame
beyond the table's largest measured rate is clipped to it and flagged.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from services.common.errors import ConfigError


@dataclass(frozen=True)
class RingParams:
    cells: int = 512  # head-direction cells on the ring (the bump sticks to cells by up to half a spacing, 0.35°)
    j0: float = -2.0  # uniform (inhibitory) part of the connections
    j1: float = 3.0  # cosine (excitatory, tuned) part: > 2 for a bump
    drive: float = 1.0  # constant input I₀
    dt: float = 0.2  # integration step, in units of τ
    steps_per_frame: int = 20  # steps per camera frame: a frame lasts 4 τ
    max_tilt: float = 0.6  # largest kernel tilt δ used (rad); the bump breaks up near 1

    def __post_init__(self) -> None:
        if self.cells < 8:
            raise ConfigError(f"ring cells={self.cells}: must be >= 8")
        if not self.j1 > 2:
            raise ConfigError(f"ring j1={self.j1}: must exceed 2 for a bump to form")
        if not self.j0 < 0:
            raise ConfigError(f"ring j0={self.j0}: must be negative (bounded bump)")
        if not (0 < self.dt <= 0.5 and self.steps_per_frame >= 1 and 0 < self.max_tilt < 1.2):
            raise ConfigError("ring dt must be in (0, 0.5], steps_per_frame >= 1, max_tilt in (0, 1.2)")


class HeadDirectionRing:
    """The ring network. ``run(tilt)`` advances one frame; ``heading`` decodes the bump."""

    def __init__(self, params: RingParams = RingParams(), heading0: float = 0.0):
        self.params = params
        self.angles = 2 * math.pi * np.arange(params.cells) / params.cells
        self._phasor = np.exp(1j * self.angles)
        # Start from a small bump at heading0 and let it form (10 frames at δ = 0).
        self.h = 0.1 * np.cos(self.angles - heading0)
        for _ in range(10):
            self.run(0.0)

    @property
    def rates(self) -> np.ndarray:
        return np.maximum(self.h, 0.0)

    @property
    def heading(self) -> float:
        """Population vector of the rates, rad in (−π, π]."""
        return float(np.angle(np.dot(self.rates, self._phasor)))

    def run(self, tilt: float) -> None:
        """One frame with the kernel tilted by ``tilt`` rad (positive turns counter-clockwise)."""
        p = self.params
        h, phasor = self.h, self._phasor
        shifted = np.exp(1j * (self.angles - tilt))
        for _ in range(p.steps_per_frame):
            rates = np.maximum(h, 0.0)
            m0 = rates.mean()
            m1 = np.dot(rates, phasor) / p.cells
            recurrent = p.j0 * m0 + p.j1 * (shifted * np.conj(m1)).real
            h += p.dt * (recurrent + p.drive - h)


@dataclass(frozen=True, eq=False)
class RingCalibration:
    """Turn per frame (rad) of the bump for each kernel tilt (rad), odd and increasing."""

    tilts: np.ndarray
    turns: np.ndarray

    @property
    def max_turn(self) -> float:
        return float(self.turns[-1])

    def tilt_for(self, turn: float) -> tuple[float, bool]:
        """The tilt that turns the bump by ``turn`` rad per frame, and whether the turn was
        beyond the ring's range (then the largest tilt, with its sign)."""
        clipped = abs(turn) > self.turns[-1]
        tilt = float(np.interp(abs(turn), self.turns, self.tilts))
        return math.copysign(tilt, turn), clipped


@functools.lru_cache(maxsize=4)
def ring_calibration(params: RingParams = RingParams(), points: int = 41, frames: int = 12) -> RingCalibration:
    """Measure the bump's turn per frame at ``points`` tilts from 0 to max_tilt (denser near 0,
    where yaw rates live): the mean over ``frames`` frames after 3 frames of settling."""
    tilts = params.max_tilt * np.linspace(0.0, 1.0, points) ** 2
    turns = np.zeros(points)
    ring = HeadDirectionRing(params)
    start = ring.h.copy()
    for k, tilt in enumerate(tilts[1:], start=1):
        ring.h = start.copy()
        for _ in range(3):
            ring.run(tilt)
        before = ring.heading
        total = 0.0
        for _ in range(frames):
            ring.run(tilt)
            now = ring.heading
            total += math.remainder(now - before, 2 * math.pi)
            before = now
        turns[k] = total / frames
    if np.any(np.diff(turns) <= 0):
        raise ConfigError(f"ring parameters {params}: the turn rate does not grow with the tilt (max_tilt too large?)")
    return RingCalibration(tilts, turns)


# The largest turn the ring makes in one of its frames: a larger yaw is integrated over as many
# ring frames as it takes (the ring follows 30° per frame within 0.13°, 60° within 0.8°, and
# its bump breaks up near 150°: docs/gridcells.md). A walk reflected off a wall turns by up to
# 180° between two frames.
MAX_TURN_PER_RING_FRAME = math.radians(30.0)


class RingHeading:
    """Heading integration by the ring: each frame's yaw becomes a tilt (via the calibration),
    the ring runs one frame (or more, for a yaw beyond MAX_TURN_PER_RING_FRAME), the heading is
    decoded from the bump."""

    def __init__(self, heading0: float = 0.0, params: RingParams = RingParams()):
        self.calibration = ring_calibration(params)
        self.ring = HeadDirectionRing(params, heading0)
        # The decoded heading of the formed bump is heading0 to numerical precision; keep the
        # offset anyway so that the first heading equals heading0 exactly.
        self.offset = math.remainder(heading0 - self.ring.heading, 2 * math.pi)
        self.clipped = 0

    def step(self, yaw: float) -> tuple[float, bool]:
        """Integrate one frame's yaw (rad); returns the decoded heading and whether the yaw
        exceeded the ring's range (it cannot: large yaws take several ring frames)."""
        frames = max(1, math.ceil(abs(yaw) / MAX_TURN_PER_RING_FRAME))
        tilt, clipped = self.calibration.tilt_for(yaw / frames)
        self.clipped += clipped
        for _ in range(frames):
            self.ring.run(tilt)
        return math.remainder(self.ring.heading + self.offset, 2 * math.pi), clipped

    @property
    def heading(self) -> float:
        return math.remainder(self.ring.heading + self.offset, 2 * math.pi)

    def checkpoint(self) -> dict:
        return {"ring_state": self.ring.h.copy(), "ring_offset": self.offset}

    def restore(self, checkpoint: dict) -> None:
        self.ring.h = np.array(checkpoint["ring_state"], dtype=np.float64)
        self.offset = float(checkpoint["ring_offset"])
