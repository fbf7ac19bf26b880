"""The calibrated lattice flow (issue 13): how the lattice of one network actually flows for
a given input velocity, measured once per parameter set, and its inverse.

The network does not move its lattice exactly along its input: the direction of the flow
deviates by a few tenths of a degree depending on the direction relative to the lattice
(more at very slow speeds, where the lattice sticks to the neuron grid), and its speed is not
exactly proportional to the input's (it saturates beyond α·|v| ≈ 0.3). Both are systematic.

`measure_flow` drives a batch of copies of the network (one per input direction, continuing
from one speed to the next) at constant velocities over a grid of directions and speeds and
records the mean decoded flow, as a complex gain c(θ, s) = flow / input (world frame: x + iy;
the lattice flows toward larger columns for +x and smaller rows for +y). A flow w is decoded
by inverting it: the input u with c(u)·u = w, by fixed-point iteration on the table
(linear in direction, cubic in speed). The table also holds the network's warm state (the
settled lattice after WARM_FRAMES zero-velocity frames on the torus, when it has finished
re-forming and no longer drifts), the one-frame lag of the flow behind a change of input, and
the rms error of the decoded velocity on a varying input (the module's precision).

Tables are cached on disk (cache_dir(): $GRIDSLAM_CACHE, else $XDG_CACHE_HOME/gridslam, else
~/.cache/gridslam), one .npz per parameter set, named by a hash of everything that shapes it;
a change of network parameters, grid or CALIBRATION_VERSION makes a new one.
"""

from __future__ import annotations

import cmath
import os
import hashlib
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from services.common.environment import cache_folder
from services.gridcells.decoders import decode_subpixel
from services.gridcells.network import GridCellError, NetworkParams, NetworkStack

log = logging.getLogger(__name__)

# Bump when the measurement changes: old cache files are then ignored.
CALIBRATION_VERSION = 3
# Zero-velocity frames after the authors' settling: the lattice re-forms into a torus-periodic
# one and its drift at rest falls from ~0.003 to < 1e-4 neurons per frame (docs/gridcells.md).
WARM_FRAMES = 200


@dataclass(frozen=True)
class CalibrationGrid:
    """Where the flow is measured: `directions` input directions evenly spaced over the circle,
    and every `axis_step_deg` within `axis_span_deg` of the sheet's axes (0°, 90°, 180°, 270°),
    where the flow's direction error changes by up to 0.3° within a degree (motion along a
    row or column of neurons keeps the lattice's phase across it: the lattice sticks);
    speeds as α·|v| (the drive of eq. 4; the default reaches the saturated range beyond 0.3);
    at each speed `settle_frames` frames are dropped after the change (the lattice's shape
    relaxes over ~10 frames after a change of speed, turning its flow by up to 0.1°: the table
    holds the steady flow) and the flow averaged
    over enough frames for the lattice to travel `travel` neurons (at least `min_frames`,
    at most `max_frames`). `check_frames` frames of a smoothly varying input then measure the
    lag and the precision."""

    directions: int = 36
    axis_span_deg: float = 6.0
    axis_step_deg: float = 1.0
    drives: tuple[float, ...] = (0.004, 0.008, 0.016, 0.03, 0.06, 0.1, 0.15, 0.2, 0.25, 0.3, 0.36)
    settle_frames: int = 10
    min_frames: int = 6
    max_frames: int = 40
    travel: float = 2.0
    check_frames: int = 300
    warm_frames: int = WARM_FRAMES

    def half_circle(self) -> np.ndarray:
        """The measured directions in [0, π), rad, increasing."""
        if self.directions < 2 or self.directions % 2:
            raise GridCellError(f"calibration directions {self.directions}: must be an even number >= 2")
        coarse = np.arange(self.directions // 2) * 360.0 / self.directions
        fine = []
        if self.axis_span_deg > 0 and self.axis_step_deg > 0:
            offsets = np.arange(self.axis_step_deg, self.axis_span_deg + 1e-9, self.axis_step_deg)
            fine = np.concatenate([axis + sign * offsets for axis in (0.0, 90.0, 180.0) for sign in (-1, 1)])
        degrees = np.concatenate([coarse, fine])
        degrees = np.unique(np.round(degrees[(degrees >= 0) & (degrees < 180)], 9))
        return np.radians(degrees)


@dataclass(frozen=True, eq=False)
class FlowTable:
    """The measured flow of one network. `gain[j, k]` is the complex flow per unit of input
    (neurons per network unit, world frame) at direction angles[j] and speed speeds[k]
    (network units per frame); `scatter[j, k]` the per-frame standard deviation of the decoded
    flow there (neurons). `lag`: the fraction of a change of flow that shows one frame late
    (measured on a turn; LagInverter).
    `noise`: rms error per frame of the decoded velocity on a varying input, network units.
    `warm_state`, `warm_field`: the network's start (n×n)."""

    params: NetworkParams
    search: int
    angles: np.ndarray
    speeds: np.ndarray
    gain: np.ndarray
    scatter: np.ndarray
    lag: float
    noise: float
    warm_state: np.ndarray
    warm_field: np.ndarray
    seconds: float = 0.0
    _lookup: tuple = field(default=(), repr=False)

    def __post_init__(self) -> None:
        angles = np.append(self.angles, self.angles[0] + 2 * math.pi)  # periodic in direction
        gain = np.vstack([self.gain, self.gain[:1]])
        # Slopes in speed for cubic Hermite interpolation (the three-point derivative on the
        # uneven grid; one-sided at the ends): the gain is curved in speed, and a straight
        # line between the tabulated speeds misses it by up to 0.03 %.
        speeds = self.speeds
        slopes = np.zeros_like(gain)
        if len(speeds) > 1:
            h = np.diff(speeds)
            d = np.diff(gain, axis=1) / h
            slopes[:, 0], slopes[:, -1] = d[:, 0], d[:, -1]
            if len(speeds) > 2:
                slopes[:, 1:-1] = (h[1:] * d[:, :-1] + h[:-1] * d[:, 1:]) / (h[:-1] + h[1:])
        object.__setattr__(self, "_lookup", (angles, gain, slopes, speeds))

    @property
    def max_speed(self) -> float:
        return float(self.speeds[-1])

    def gain_at(self, angle: float, speed: float) -> complex:
        """c(θ, s): linear in direction, cubic (Hermite) in speed; constant below the slowest
        and beyond the fastest tabulated speed."""
        angles, gain, slopes, speeds = self._lookup
        angle = angle % (2 * math.pi)
        j = min(max(int(np.searchsorted(angles, angle, side="right")) - 1, 0), len(angles) - 2)
        a = (angle - angles[j]) / (angles[j + 1] - angles[j])
        if len(speeds) == 1 or speed <= speeds[0]:
            values = gain[j, 0], gain[j + 1, 0]
        elif speed >= speeds[-1]:
            values = gain[j, -1], gain[j + 1, -1]
        else:
            k = int(np.searchsorted(speeds, speed)) - 1
            h = speeds[k + 1] - speeds[k]
            t = (speed - speeds[k]) / h
            basis = (2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2)
            values = tuple(basis[0] * gain[i, k] + basis[1] * h * slopes[i, k] + basis[2] * gain[i, k + 1] + basis[3] * h * slopes[i, k + 1]
                           for i in (j, j + 1))
        return complex((1 - a) * values[0] + a * values[1])

    def flow(self, velocity: complex) -> complex:
        """The flow (neurons per frame, world frame) the table predicts for an input velocity."""
        if velocity == 0:
            return 0j
        return self.gain_at(cmath.phase(velocity), abs(velocity)) * velocity

    def invert(self, flow: complex, iterations: int = 6) -> complex:
        """The input velocity (network units per frame, world frame) whose flow is ``flow``."""
        if flow == 0:
            return 0j
        velocity = flow / self.gain_at(cmath.phase(flow), abs(flow) / abs(self.gain[0, 0]))
        for _ in range(iterations):
            velocity = flow / self.gain_at(cmath.phase(velocity), abs(velocity))
        return velocity

    # --- persistence -------------------------------------------------------------------------
    def save(self, path: Path) -> Path:
        tmp = path.with_name(path.name + ".tmp")
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as handle:
            np.savez_compressed(handle, params=json.dumps(asdict(self.params)), search=self.search, angles=self.angles, speeds=self.speeds,
                     gain=self.gain, scatter=self.scatter, lag=self.lag, noise=self.noise, warm_state=self.warm_state,
                     warm_field=self.warm_field, seconds=self.seconds, version=CALIBRATION_VERSION)
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: Path) -> FlowTable:
        with np.load(path, allow_pickle=False) as data:
            if int(data["version"]) != CALIBRATION_VERSION:
                raise ValueError(f"calibration version {int(data['version'])}, expected {CALIBRATION_VERSION}")
            return cls(NetworkParams(**json.loads(str(data["params"]))), int(data["search"]), data["angles"], data["speeds"],
                       data["gain"], data["scatter"], float(data["lag"]), float(data["noise"]), data["warm_state"],
                       data["warm_field"], float(data["seconds"]))


def lattice_search(params: NetworkParams, field_: np.ndarray, limit: int = 9) -> int:
    """Shift search range for a module: below half its lattice period (a larger window can
    take a neighbouring lattice peak), at most ``limit``."""
    n = field_.shape[0]
    power = np.abs(np.fft.fft2(field_ - field_.mean())) ** 2
    k = np.fft.fftfreq(n) * n
    radius = np.hypot(k[:, None], k[None, :])
    power[(radius == 0) | (radius > 0.2 * n)] = 0
    period = n / radius.flat[int(np.argmax(power))]
    return int(max(2, min(limit, math.floor(period / 2 - 1))))


def warm_network(params: NetworkParams, frames: int = WARM_FRAMES) -> NetworkStack:
    """One network settled as the authors do, then run ``frames`` zero-velocity frames."""
    network = NetworkStack(params)
    for _ in range(frames):
        network.run((0.0, 0.0))
    return network


def measure_flow(params: NetworkParams, grid: CalibrationGrid = CalibrationGrid(), *, search: int | None = None) -> FlowTable:
    """Measure the flow table of one network (see the module docstring). Deterministic."""
    started = time.perf_counter()
    warm = warm_network(params, grid.warm_frames)
    warm_state, warm_field = warm.state[0], warm.fields[0]
    search = lattice_search(params, warm_field) if search is None else search
    half_angles = grid.half_circle()
    angles = np.concatenate([half_angles, half_angles + math.pi])
    speeds = np.array(grid.drives) / params.alpha  # network units per frame
    # The dynamics are symmetric under v → −v (a point reflection of the sheet maps each
    # direction population onto the opposite one), and so is the flow: measure half the circle.
    half = len(half_angles)
    unit = np.exp(1j * half_angles)
    batch = NetworkStack((params,) * half, settle=False)
    batch.state = np.repeat(warm_state[None], half, axis=0)
    batch.set_field(np.repeat(warm_field[None], half, axis=0))
    gain = np.zeros((half, len(speeds)), dtype=complex)
    scatter = np.zeros((half, len(speeds)))
    nominal = 0.383 * params.alpha * params.steps_per_frame  # neurons per frame per network unit (integrator.LATTICE_RATE)
    measured = len(speeds)
    for k, speed in enumerate(speeds):
        frames = int(np.clip(math.ceil(grid.travel / (nominal * speed)), grid.min_frames, grid.max_frames))
        previous = None
        flows = np.zeros((frames, half), dtype=complex)
        for frame in range(grid.settle_frames + frames):
            velocities = speed * unit
            fields = batch.run(np.column_stack([velocities.real, velocities.imag]))
            if frame >= grid.settle_frames:
                for j in range(half):
                    dx, dy = decode_subpixel(previous[j], fields[j], search)
                    flows[frame - grid.settle_frames, j] = complex(dx, -dy)
            previous = fields
        if np.max(np.abs(np.r_[flows.real.ravel(), flows.imag.ravel()])) >= search - 0.5:
            # The flow reached the edge of the search window: this speed and faster ones are
            # beyond what the module can read; the table ends at the previous speed.
            measured = k
            break
        gain[:, k] = flows.mean(axis=0) / (speed * unit)
        scatter[:, k] = np.abs(flows - flows.mean(axis=0)).std(axis=0) if frames > 1 else 0.0
        log.debug("calibration λ=%g: drive %.3g, %d frames, mean |gain| %.4g", params.lam, speed * params.alpha, frames, np.abs(gain[:, k]).mean())
    if measured < 2:
        raise GridCellError(f"calibration of λ={params.lam}: the flow leaves the ±{search} search already at drive "
                            f"{grid.drives[measured]}; lower the drives")
    speeds, gain, scatter = speeds[:measured], gain[:, :measured], scatter[:, :measured]
    gain, scatter = np.vstack([gain, gain]), np.vstack([scatter, scatter])
    table = FlowTable(params, search, angles, speeds, gain, scatter, 0.0, 0.0, warm_state.astype(np.float32), warm_field.astype(np.float32))
    lag, noise = _check_sequence(table, grid.check_frames)
    seconds = time.perf_counter() - started
    log.info("calibrated the lattice flow of λ=%g (n=%d, α=%g) in %.1f s: lag %.4f, noise %.3g units/frame",
             params.lam, params.n, params.alpha, seconds, lag, noise)
    return FlowTable(params, search, angles, speeds, gain, scatter, lag, noise, table.warm_state, table.warm_field, seconds)


def check_velocities(frames: int, speed: float, seed: int = 0) -> np.ndarray:
    """A smoothly varying input (complex, network units per frame): speed and direction as
    Ornstein-Uhlenbeck processes around ``speed`` (0 to 2×) and a slowly turning heading."""
    rng = np.random.default_rng(seed)
    velocities = np.zeros(frames, dtype=complex)
    level, heading, turn = 1.0, 0.0, 0.0
    for k in range(frames):
        level = float(np.clip(1.0 + 0.9 * (level - 1.0) + 0.15 * rng.normal(), 0.0, 2.0))
        turn = 0.8 * turn + 0.05 * rng.normal()
        heading += turn
        velocities[k] = speed * level * cmath.exp(1j * heading)
    return velocities


def check_flows(table: FlowTable, velocities: np.ndarray) -> np.ndarray:
    """The decoded flow (complex, neurons per frame) of the table's warm network driven with
    ``velocities`` (complex, network units per frame), one frame each."""
    network = NetworkStack(table.params, settle=False)
    network.state = table.warm_state[None]
    network.set_field(table.warm_field[None])
    previous = network.fields[0]
    measured = np.zeros(len(velocities), dtype=complex)
    for k, velocity in enumerate(velocities):
        field_ = network.run((velocity.real, velocity.imag))[0]
        dx, dy = decode_subpixel(previous, field_, table.search)
        measured[k] = complex(dx, -dy)
        previous = field_
    return measured


def lag_components(table: FlowTable, velocities: np.ndarray, measured: np.ndarray) -> tuple[float, float]:
    """The one-frame lags (along, across) of measured flows: flow_k ≈ F_k + c·(F_{k−1} − F_k),
    F the table's flow of each velocity, the change and the residual split along and across
    F_k, each coefficient by least squares: a change of speed, a turn."""
    predicted = np.array([table.flow(v) for v in velocities])
    moving = np.abs(predicted[1:]) > 0
    direction = np.where(moving, predicted[1:] / np.where(moving, np.abs(predicted[1:]), 1), 0)
    change = (predicted[:-1] - predicted[1:]) * np.conj(direction)
    residual = (measured[1:] - predicted[1:]) * np.conj(direction)
    along, across = (float(np.dot(part(residual), part(change)) / max(np.dot(part(change), part(change)), 1e-30))
                     for part in (np.real, np.imag))
    return along, across


def _check_sequence(table: FlowTable, frames: int) -> tuple[float, float]:
    """Drive the warm network with check_velocities at half the linear range (α|v| about
    0.15) and compare the decoded flow with the table's: the lag c (lag_components' lag
    across the direction of travel, a turn) and the rms error of the velocity decoded with it
    (network units).

    Across, because the direction follows a turn with about the same lag at every speed (2 %
    from α|v| = 0.02 to 0.2 at n = 128); a change of speed shows more (2 % to 4 %), but taken
    out with its own coefficient along each frame's direction it does not sum to the
    displacement (docs/gridcells.md, "The step length from the lattice")."""
    if frames < 3:
        return 0.0, 0.0
    velocities = check_velocities(frames, 0.15 / table.params.alpha)
    measured = check_flows(table, velocities)
    lag = lag_components(table, velocities, measured)[1]
    decoded = LagInverter(table, lag)
    errors = np.array([decoded(w) - v for w, v in zip(measured, velocities)])
    return lag, float(np.sqrt(np.mean(np.abs(errors[1:]) ** 2)))


class LagInverter:
    """Per-frame decoding with the table: flow → input velocity, with the one-frame lag taken
    out. The model flow_k = F_k + c·(F_{k−1} − F_k) (F_{k−1} the previous frame's own flow) is
    solved exactly, F_k = (flow_k − c·F_{k−1}) / (1 − c), and conserves the displacement: the
    own flows sum to the decoded ones plus c times the last own flow, whatever the path, so the
    per-frame noise of the flow does not accumulate through the lag."""

    def __init__(self, table: FlowTable, lag: float | None = None):
        self.table = table
        self.lag = table.lag if lag is None else float(lag)
        self.previous_flow = 0j

    def __call__(self, flow: complex) -> complex:
        own = (flow - self.lag * self.previous_flow) / (1.0 - self.lag)
        self.previous_flow = own
        return self.table.invert(own)


# --- the disk cache ----------------------------------------------------------------------------
def cache_dir() -> Path:
    """The folder of measured flow tables (services/common/environment.py, cache_folder)."""
    return cache_folder()


def cache_key(params: NetworkParams, grid: CalibrationGrid, search: int | None) -> str:
    text = json.dumps({"version": CALIBRATION_VERSION, "params": asdict(params), "grid": asdict(grid), "search": search},
                      sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# Tables of the default network's modules (`gridslam calibrate --modules 4 --out <this folder>`),
# shipped so that the first run does not spend a minute per module measuring them.
PACKAGED = Path(__file__).with_name("flow_tables")


def flow_table_path(folder: Path, params: NetworkParams, grid: CalibrationGrid = CalibrationGrid(), search: int | None = None) -> Path:
    return Path(folder) / f"flow-n{params.n}-lam{params.lam:.4g}-alpha{params.alpha:.4g}-{cache_key(params, grid, search)}.npz"


def flow_table(params: NetworkParams, grid: CalibrationGrid = CalibrationGrid(), *, search: int | None = None,
               cache: Path | None | bool = True) -> FlowTable:
    """The flow table of ``params``: from the disk cache (or the tables shipped with the
    package) when they hold it, else measured and written to the cache. ``cache`` False:
    measure, keep nothing; a Path: that folder instead of cache_dir()."""
    folder = cache_dir() if cache is True else (Path(cache) if cache else None)
    path = flow_table_path(folder, params, grid, search) if folder else None
    candidates = [p for p in (path, flow_table_path(PACKAGED, params, grid, search) if cache is True else None) if p is not None]
    for candidate in candidates:
        if candidate.exists():
            try:
                table = FlowTable.load(candidate)
                log.debug("lattice flow table from %s", candidate)
                return table
            except (OSError, ValueError, KeyError) as error:
                log.warning("%s: unreadable calibration (%s): measuring it again", candidate, error)
    log.info("calibrating the lattice flow of λ=%g (once per parameter set; cached in %s)", params.lam, folder or "memory")
    table = measure_flow(params, grid, search=search)
    if path is not None:
        try:
            table.save(path)
        except OSError as error:
            log.warning("%s: cannot cache the calibration (%s); it will be measured again next time", path, error.strerror or error)
    return table
