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
frame x, y with heading measured from world +x, wrapped to [−π, π).
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np

from services.common.odometry import DeadReckoning, GridStep, PathIntegrator, Pose2D, body_to_world, turn_first
from services.gridcells.calibration import CalibrationGrid, FlowTable, LagInverter, flow_table
from services.common import stages
from services.common.stages import HEADING_MODELS, STEP_SOURCES
from services.gridcells.decoders import DECODERS, SubpixelReader
from services.gridcells.heading import RingHeading
from services.gridcells.network import GridCellError, GridNetwork, NetworkParams, NetworkStack

log = logging.getLogger(__name__)

__all__ = [
    "DECODER_NAMES",
    "HEADING_MODELS",
    "STEP_SOURCES",
    "DeadReckoning",
    "GridCellError",
    "GridCellIntegrator",
    "GridStep",
    "Pose2D",
    "auto_velocity_scale",
    "module_params",
    "turn_first",
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


DECODER_NAMES = stages.DECODERS   # the decoders of decoders.py and calibrated (calibration.py)
# Grid modules differ in their velocity gain: module k has α·MODULE_RATIO^e for e in
# MODULE_EXPONENTS[:N]. The network's lattice period is the same (~25 neurons), so its period
# in the world, the grid spacing, is divided by the gain (Burak & Fiete 2009): neighbouring
# spacings differ by the ratio ≈ 1.4 measured between the grid modules of rodents (Stensola et
# al. 2012). Modules made by changing λ instead (a lattice period of ~18 or ~35 neurons on the
# 128² torus) flow far less regularly: their calibrated velocity is 2× and 10× noisier.
MODULE_RATIO = 1.4
MODULE_EXPONENTS = (0, -1, 1, -2)
MAX_MODULES = len(MODULE_EXPONENTS)


# Module 0's sheet is turned by this much against the world. Within ~4° of the sheet's axes
# (rows and columns, every 90°) the lattice's flow changes its direction and speed sharply with
# the direction of travel (by up to 0.3° and 0.1 % within a degree), more than a table can
# follow; routes run mostly along their start heading and across it (roads, corridors), so
# the sheet's axes are kept off those. (The axes of rats' grids are turned by about 7.5°
# against the walls of their box; Stensola et al. 2015.)
MODULE_ORIENTATION = math.radians(7.5)


# Within AXIS_BAND of its sheet's axes a module's calibrated direction errs by up to ~0.1° per
# frame (the table cannot follow the flow there); with several modules, such a module's
# estimate counts AXIS_WEIGHT times its usual weight (at most one of N ≤ 3 modules is there).
AXIS_BAND = math.radians(6.0)
AXIS_WEIGHT = 0.05


def _near_axis(velocity: complex) -> bool:
    """Whether a velocity in a module's sheet frame runs within AXIS_BAND of the sheet's axes."""
    angle = math.atan2(velocity.imag, velocity.real) % (math.pi / 2)
    return min(angle, math.pi / 2 - angle) < AXIS_BAND


def module_rotations(modules: int) -> np.ndarray:
    """The orientation of each module's sheet against the world, rad: MODULE_ORIENTATION +
    k·90°/N, so that any direction of travel is near the sheet axes of one module at most (grid
    modules differ in orientation too; Stensola et al. 2012)."""
    return MODULE_ORIENTATION + np.arange(modules) * (math.pi / 2) / modules


def module_params(params: NetworkParams, modules: int) -> tuple[NetworkParams, ...]:
    """The parameters of ``modules`` grid modules around ``params`` (module 0 is ``params``)."""
    if not 1 <= modules <= MAX_MODULES:
        raise GridCellError(f"modules={modules}: choose 1 to {MAX_MODULES}")
    return tuple(replace(params, alpha=params.alpha * MODULE_RATIO**e) if e else params for e in MODULE_EXPONENTS[:modules])


class GridCellIntegrator(PathIntegrator):
    """The grid-cell odometry. ``decoder`` is "paper", "fft", "subpixel" (see decoders.py) or
    "calibrated" (subpixel's shift, then the inverse of the measured flow: calibration.py).

    ``paper`` reproduces the authors' code: a float64 network (their doubles), and the first
    frame only stores the pattern. The other decoders use the fast float32 network
    (network.NetworkStack) and compare the first frame with the start field, so the first
    frame's motion is not lost; ``calibrated`` starts from the warm state of its calibration.

    ``step``: "odometry" (eq. 5: the step length from the ego-motion, the direction from the
    lattice) or "lattice" (the whole displacement from the calibrated flow: the network alone
    integrates the path; needs the calibrated decoder; a frame that no module can read, its flow
    beyond every module's table or search window, is flagged saturated and takes its length
    from the ego-motion as with "odometry"). ``modules`` (calibrated decoder):
    N networks of different grid spacings (velocity gains: module_params) and orientations
    (module_rotations), run as one batch, each decoded; their velocity estimates are combined
    weighted by their precision (1/noise² of their calibration), a module near its sheet's
    axes or beyond its table counting less or not at all. ``heading``: "sum" (heading += yaw,
    the paper's) or "ring" (a head-direction ring attractor integrates the yaw: heading.py).
    ``network``: the network to drive (a GridNetwork for `paper`, a NetworkStack otherwise;
    default a new one).

    ``velocity_scale`` converts input units to network units (see auto_velocity_scale); the
    step length stays in input units. A frame is ``saturated`` when the network is driven
    beyond its linear range (α·|v|·scale > LINEAR_LIMIT), a decoded shift reaches the edge of
    its search (|dx| or |dy| ≥ search − ½), or (ring) the yaw exceeds the ring's range;
    ``saturations`` counts them and the first one is logged as a warning. With
    velocity_scale = 1 the authors' NuBot input (metres) saturates from about 0.15 m per frame on.
    """

    error = GridCellError

    def __init__(
        self,
        params: NetworkParams = NetworkParams(),
        decoder: str = "subpixel",
        velocity_scale: float = 1.0,
        heading0: float = 0.0,
        network: GridNetwork | NetworkStack | None = None,
        *,
        search: int = 9,
        step: str = "odometry",
        modules: int = 1,
        heading: str = "sum",
        calibration_cache=True,
        calibration_grid: CalibrationGrid = CalibrationGrid(),
    ):
        if decoder not in DECODER_NAMES:
            raise GridCellError(f"unknown decoder '{decoder}': choose one of {', '.join(DECODER_NAMES)}")
        if step not in STEP_SOURCES:
            raise GridCellError(f"unknown step source '{step}': choose one of {', '.join(STEP_SOURCES)}")
        if heading not in HEADING_MODELS:
            raise GridCellError(f"unknown heading model '{heading}': choose one of {', '.join(HEADING_MODELS)}")
        if decoder != "calibrated" and (step == "lattice" or modules != 1):
            raise GridCellError("--step lattice and --modules > 1 need the calibrated decoder (--decoder calibrated)")
        if not (math.isfinite(velocity_scale) and velocity_scale > 0):
            raise GridCellError(f"velocity scale {velocity_scale}: must be a positive number (network units per metre)")
        super().__init__(heading0)
        self.decoder, self.step_source, self.heading_model = decoder, step, heading
        self.velocity_scale = float(velocity_scale)
        self.search = int(search)
        self.ring = RingHeading(self._pose.heading) if heading == "ring" else None
        self.tables: tuple[FlowTable, ...] = ()
        if decoder == "paper":
            self.network = network or GridNetwork(params, dtype=np.float64)
            self.params = self.network.params
            self._previous = None
            self._searches = (self.search,)
        elif decoder == "calibrated":
            self.tables = tuple(flow_table(p, calibration_grid, cache=calibration_cache) for p in module_params(params, modules))
            self.rotations = np.exp(1j * module_rotations(modules))  # world → module k: × rotations[k]
            self.network = NetworkStack(tuple(t.params for t in self.tables), settle=False)
            self.network.state = np.stack([t.warm_state for t in self.tables])
            self.network.set_field(np.stack([t.warm_field for t in self.tables]))
            self.params = params
            self._inverters = [LagInverter(t) for t in self.tables]
            weights = np.array([1.0 / max(t.noise, 1e-12) ** 2 for t in self.tables])
            self.weights = weights / weights.sum()
            self._previous = self.network.fields
            self._searches = tuple(min(self.search, t.search) for t in self.tables)
        else:
            self.network = network or NetworkStack(params)
            self.params = self.network.params
            self._previous = self.network.fields
            self._searches = (self.search,)
        self._decode = DECODERS[decoder] if decoder in ("paper", "fft") else None
        self._readers = self._make_readers()

    def _make_readers(self) -> list[SubpixelReader] | None:
        """subpixel and calibrated: one reader per module (each field transformed once)."""
        if self._decode is not None or self._previous is None:
            return None
        return [SubpixelReader(previous, search) for previous, search in zip(self._previous, self._searches)]

    @property
    def activity(self) -> np.ndarray:
        """The current rectified field f of module 0 (n×n copy)."""
        return self.network.field if isinstance(self.network, GridNetwork) else self.network.fields[0]

    def step(self, forward: float, left: float, yaw: float) -> GridStep:
        if self.ring is None:
            return super().step(forward, left, yaw)
        self._finite(forward=forward, left=left, yaw=yaw)
        heading, clipped = self.ring.step(yaw)
        vx, vy = body_to_world(forward, left, heading)
        return self._advance(vx, vy, heading, clipped)

    def step_world(self, vx: float, vy: float, heading: float | None = None) -> GridStep:
        if self.ring is not None and heading is not None:
            # World-frame inputs with a heading: the ring follows the heading's change.
            self._finite(vx=vx, vy=vy, heading=heading)
            heading, clipped = self.ring.step(math.remainder(heading - self._pose.heading, 2 * math.pi))
            return self._advance(vx, vy, heading, clipped)
        return super().step_world(vx, vy, heading)

    def _fields(self, vx: float, vy: float) -> np.ndarray:
        scale = self.velocity_scale
        if isinstance(self.network, GridNetwork):
            return self.network.run((vx * scale, vy * scale))[None]
        if self.decoder == "calibrated":
            velocities = complex(vx, vy) * scale * self.rotations
            return self.network.run(np.column_stack([velocities.real, velocities.imag]))
        return self.network.run((vx * scale, vy * scale))

    def _advance(self, vx: float, vy: float, heading: float, clipped: bool = False) -> GridStep:
        scale = self.velocity_scale
        fields = self._fields(vx, vy)
        self.frames += 1
        previous, self._previous = self._previous, fields
        if previous is None:  # the authors' first frame only stores the pattern
            self._pose = Pose2D(self._pose.x, self._pose.y, heading)
            return GridStep(self._pose, (0.0, 0.0), 0.0, False)
        if self._readers is not None:
            shifts = [reader(field) for reader, field in zip(self._readers, fields)]
        else:
            shifts = [self._decode(previous[i], fields[i], search) for i, search in enumerate(self._searches)]
        dx, dy = shifts[0]
        speed = math.hypot(vx, vy)
        saturated = self.params.alpha * speed * scale > LINEAR_LIMIT or clipped or max(abs(dx), abs(dy)) >= self._searches[0] - 0.5
        x, y, step_length = self._pose.x, self._pose.y, 0.0
        if self.decoder == "calibrated":
            estimates = [inverter(complex(a, -b)) for inverter, (a, b) in zip(self._inverters, shifts)]
            # A module whose flow left its table or reached its search edge is left out of
            # this frame's combination (the others still read it), unless all did.
            within = np.array([abs(u) <= t.max_speed and max(abs(a), abs(b)) < search - 0.5
                               for u, t, (a, b), search in zip(estimates, self.tables, shifts, self._searches)])
            weights = self.weights * within if within.any() else self.weights
            if len(estimates) > 1:  # near its sheet's axes a module's flow is erratic: lean on the others
                weights = weights * np.array([AXIS_WEIGHT if _near_axis(u) else 1.0 for u in estimates])
            velocity = sum(w * u / rotation for w, u, rotation in zip(weights, estimates, self.rotations)) / weights.sum() / scale
            saturated = saturated or not within.any()
            if self.step_source == "lattice" and within.any():
                x, y, step_length = x + velocity.real, y + velocity.imag, abs(velocity)
            elif velocity != 0:  # eq. 5 with the calibrated direction (lattice step: no module could read its speed)
                x += speed * velocity.real / abs(velocity)
                y += speed * velocity.imag / abs(velocity)
                step_length = speed
        else:
            length = math.hypot(dx, dy)
            if length > 0:  # eq. 5: step length from the ego-motion, direction from the lattice
                x += speed * dx / length
                y -= speed * dy / length
                step_length = speed
        if saturated:
            self.saturations += 1
            level = logging.WARNING if self.saturations == 1 else logging.DEBUG
            log.log(level, "frame %d: lattice flow saturated (network speed α·|v| = %.3g, linear up to %.2g; shift %.2f, %.2f%s; "
                    "lower the velocity scale)", self.frames, self.params.alpha * speed * scale, LINEAR_LIMIT, dx, dy,
                    "; yaw beyond the ring's range" if clipped else "")
        self._pose = Pose2D(x, y, heading)
        return GridStep(self._pose, (dx, dy), step_length, saturated)

    def checkpoint(self) -> dict:
        """The pose and counters, the network activity, the last fields and the decoders' and
        ring's state."""
        checkpoint = {**super().checkpoint(), "state": self.network.state, "previous": self._previous}
        if self.decoder == "calibrated":
            checkpoint["previous_flow"] = np.array([inverter.previous_flow for inverter in self._inverters])
        if self.ring is not None:
            checkpoint |= self.ring.checkpoint()
        return checkpoint

    def restore(self, checkpoint: dict) -> None:
        super().restore(checkpoint)
        state = np.asarray(checkpoint["state"])
        self.network.state = state[0] if isinstance(self.network, GridNetwork) and state.ndim == 3 else state
        previous = checkpoint["previous"]
        self._previous = None if previous is None else np.asarray(previous).reshape((-1,) + np.shape(previous)[-2:])
        self._readers = self._make_readers()
        if self.decoder == "calibrated" and "previous_flow" in checkpoint:
            for inverter, flow in zip(self._inverters, np.asarray(checkpoint["previous_flow"]).ravel()):
                inverter.previous_flow = complex(flow)
        if self.ring is not None and "ring_state" in checkpoint:
            self.ring.restore(checkpoint)


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
