"""The paper's simulation (Lu et al., ROBIO 2016): an agent moving randomly within a
circle of radius 2 m at up to 2.5 m/s; and the grid-cell analysis of its Fig. 4: the firing
map of one neuron over the arena and its gridness score (Sargolini et al., Science 2006).

Pure numpy/scipy: walks are arrays, maps are arrays, scores are floats.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft

from services.common.geometry import wrap


@dataclass(frozen=True)
class WalkParams:
    """A random walk in a circular arena (defaults: the paper's simulation).

    The frame period sets the size of a frame's step: 20 ms (50 Hz, the sampling of the
    Sargolini rat recordings) makes the top speed 5 cm per frame, which the automatic
    velocity scale maps to a lattice shift of a few neurons per frame, the range the authors'
    centimetre inputs give their network (docs/gridcells.md, "The paper's simulation").
    """

    radius_m: float = 2.0  # arena radius (paper)
    max_speed_m_s: float = 2.5  # speed limit (paper)
    frame_period_s: float = 0.02  # one frame, s
    mean_speed_m_s: float = 1.0  # the speed process's mean (an Ornstein-Uhlenbeck process)
    speed_std_m_s: float = 0.6  # its stationary standard deviation
    speed_tau_s: float = 1.0  # its correlation time
    turn_std_rad_s: float = 2.0  # stationary standard deviation of the turning rate
    turn_tau_s: float = 0.5  # its correlation time


@dataclass(frozen=True, eq=False)
class Walk:
    """N frames of a walk: positions (N, 2) m, heading (N,) rad (the direction of travel),
    stamps (N,) s. Frame 0 is the start (the centre); frame k moved from k-1."""

    stamps: np.ndarray
    positions: np.ndarray
    heading: np.ndarray

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def body_increments(self) -> np.ndarray:
        """(N, 3) forward, left, yaw per frame: the agent moves along its heading, so the
        step is all forward; row 0 is zero. The yaw is the heading change into the frame."""
        steps = np.vstack([[0.0, 0.0], np.diff(self.positions, axis=0)])
        yaw = np.concatenate([[0.0], wrap(np.diff(self.heading))])
        return np.column_stack([np.hypot(steps[:, 0], steps[:, 1]), np.zeros(len(self)), yaw])

    def path_length(self) -> float:
        return float(np.hypot(*np.diff(self.positions, axis=0).T).sum())

    def head(self, n_frames: int) -> Walk:
        """The first `n_frames` frames."""
        return Walk(self.stamps[:n_frames], self.positions[:n_frames], self.heading[:n_frames])


def random_walk(n_frames: int, seed: int = 0, params: WalkParams = WalkParams()) -> Walk:
    """A seeded random walk inside the circle: speed and turning rate are Ornstein-Uhlenbeck
    processes (smooth, like an animal's; cf. ratinabox's random motion model), the speed is
    clipped to [0, max_speed], and at the wall the direction of travel is reflected
    specularly so the agent stays inside."""
    if n_frames < 1:
        raise ValueError(f"a walk needs at least one frame, got {n_frames}")
    rng = np.random.default_rng(seed)
    p = params
    dt = p.frame_period_s
    speed_decay, turn_decay = math.exp(-dt / p.speed_tau_s), math.exp(-dt / p.turn_tau_s)
    speed_kick = p.speed_std_m_s * math.sqrt(1.0 - speed_decay**2)
    turn_kick = p.turn_std_rad_s * math.sqrt(1.0 - turn_decay**2)
    positions = np.zeros((n_frames, 2))
    heading = np.zeros(n_frames)
    speed, turn, direction = p.mean_speed_m_s, 0.0, rng.uniform(-math.pi, math.pi)
    heading[0] = direction
    for k in range(1, n_frames):
        speed = p.mean_speed_m_s + (speed - p.mean_speed_m_s) * speed_decay + speed_kick * rng.normal()
        speed = min(max(speed, 0.0), p.max_speed_m_s)
        turn = turn * turn_decay + turn_kick * rng.normal()
        direction += turn * dt
        step = speed * dt * np.array([math.cos(direction), math.sin(direction)])
        target = positions[k - 1] + step
        if np.hypot(*target) > p.radius_m:
            # Reflect the direction about the wall's tangent at the crossing point.
            normal = target / np.hypot(*target)
            reflected = step - 2.0 * np.dot(step, normal) * normal
            direction = math.atan2(reflected[1], reflected[0])
            target = positions[k - 1] + reflected
            if np.hypot(*target) > p.radius_m:  # a grazing step: stay put this frame
                target = positions[k - 1]
        positions[k] = target
        heading[k] = direction
    stamps = np.arange(n_frames) * dt
    return Walk(stamps, positions, wrap(heading))


# --- firing maps and gridness -----------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class FiringMap:
    """A rate map: mean activity per spatial bin (NaN where the agent never was); `edges`
    are the bin edges (m) of both axes."""

    rate: np.ndarray
    occupancy: np.ndarray
    edges: np.ndarray


def firing_map(positions: np.ndarray, activity: np.ndarray, extent_m: float, bin_m: float = 0.05, smooth_bins: float = 1.0) -> FiringMap:
    """Rate map of one neuron: the activity summed per bin divided by the occupancy, both
    smoothed with a Gaussian of `smooth_bins` bins first; bins never visited are NaN. The
    map covers [-extent_m, extent_m]² around the origin, rows along y, columns along x."""
    from scipy import ndimage   # here, not at the top: the container image has no scipy.ndimage (docs/deploy.md)

    n_bins = int(math.ceil(2 * extent_m / bin_m))
    edges = np.linspace(-extent_m, extent_m, n_bins + 1)
    occupancy, _, _ = np.histogram2d(positions[:, 0], positions[:, 1], bins=(edges, edges))
    total, _, _ = np.histogram2d(positions[:, 0], positions[:, 1], bins=(edges, edges), weights=activity)
    visited = occupancy > 0
    if smooth_bins > 0:
        occupancy_s = ndimage.gaussian_filter(occupancy, smooth_bins, mode="constant")
        total_s = ndimage.gaussian_filter(total, smooth_bins, mode="constant")
    else:
        occupancy_s, total_s = occupancy, total
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(visited, total_s / occupancy_s, np.nan)
    # Index [i, j] is x bin i, y bin j (histogram2d); transpose so rows are y, as images are.
    return FiringMap(rate.T, occupancy.T, edges)


def autocorrelogram(rate: np.ndarray) -> np.ndarray:
    """Spatial autocorrelogram of a rate map with NaN bins (Sargolini et al. 2006, SOM): the
    Pearson correlation of the map with itself shifted by every (dy, dx), over the bins
    both copies visited; lags with fewer than 20 overlapping bins are NaN. Shape
    (2H−1, 2W−1), zero lag at the centre. Computed for all lags at once by FFT."""
    valid = np.isfinite(rate).astype(float)
    values = np.where(valid > 0, rate, 0.0)

    shape = (2 * rate.shape[0] - 1, 2 * rate.shape[1] - 1)

    def corr(a, b):  # full linear cross-correlation: a convolved with b flipped, by FFT
        return scipy.fft.irfft2(scipy.fft.rfft2(a, shape) * scipy.fft.rfft2(b[::-1, ::-1], shape), shape)

    n = corr(valid, valid)
    sum_a, sum_b = corr(values, valid), corr(valid, values)
    sum_aa, sum_bb = corr(values**2, valid), corr(valid, values**2)
    sum_ab = corr(values, values)
    with np.errstate(invalid="ignore", divide="ignore"):
        covariance = n * sum_ab - sum_a * sum_b
        variance = np.sqrt(np.clip(n * sum_aa - sum_a**2, 0, None) * np.clip(n * sum_bb - sum_b**2, 0, None))
        result = covariance / variance
    n = np.rint(n)
    result[(n < 20) | ~np.isfinite(result)] = np.nan
    return result


@dataclass(frozen=True)
class Gridness:
    """Gridness score and the annulus it was measured on (autocorrelogram bins)."""

    score: float
    spacing_bins: float
    inner_radius_bins: float
    outer_radius_bins: float
    correlations: dict[int, float]


def gridness(rate: np.ndarray) -> Gridness:
    """The standard gridness score (Sargolini et al., Science 2006; Langston et al. 2010):
    on the autocorrelogram, keep the annulus around the six peaks nearest the centre (the
    central peak excluded), correlate it with itself rotated by 30°, 60°, 90°, 120° and 150°,
    and score min(r60, r120) − max(r30, r90, r150). Hexagonal maps score high (up to 2),
    square and irregular ones low or negative."""
    from scipy import ndimage   # as in firing_map

    ac = autocorrelogram(rate)
    cy, cx = (np.array(ac.shape) - 1) / 2.0
    yy, xx = np.indices(ac.shape)
    radius = np.hypot(yy - cy, xx - cx)
    # The central peak ends where the radial mean first falls below zero (or its minimum).
    bins = np.arange(0, int(radius.max()) + 1)
    which = np.digitize(radius.ravel(), bins) - 1
    finite = np.isfinite(ac.ravel())
    radial = np.array([np.mean(ac.ravel()[(which == b) & finite]) if np.any((which == b) & finite) else np.nan for b in bins])
    below = np.flatnonzero(radial < 0)
    inner = float(bins[below[0]]) if len(below) else float(bins[np.nanargmin(radial)])
    # Peaks outside the central one: local maxima (3×3) with a positive correlation.
    filled = np.nan_to_num(ac, nan=-np.inf)
    is_peak = (filled == ndimage.maximum_filter(filled, size=3)) & (filled > 0) & (radius > inner)
    peak_radii = np.sort(radius[is_peak])
    if len(peak_radii) < 1:
        return Gridness(float("nan"), float("nan"), inner, float("nan"), {})
    nearest = peak_radii[: min(6, len(peak_radii))]
    spacing = float(np.median(nearest))
    outer = min(1.25 * float(nearest.max()), float(min(cy, cx)))
    annulus = (radius >= inner) & (radius <= outer)
    # Fill NaN with 0 for the rotation; compare only bins finite in both copies.
    rotated_source = np.nan_to_num(ac, nan=0.0)
    nan_mask = ~np.isfinite(ac)
    correlations = {}
    for angle in (30, 60, 90, 120, 150):
        rotated = ndimage.rotate(rotated_source, angle, reshape=False, order=1, mode="constant", cval=0.0)
        rotated_nan = ndimage.rotate(nan_mask.astype(float), angle, reshape=False, order=0, mode="constant", cval=1.0) > 0.5
        use = annulus & ~nan_mask & ~rotated_nan
        a, b = ac[use], rotated[use]
        correlations[angle] = float(np.corrcoef(a, b)[0, 1]) if len(a) > 2 and a.std() > 0 and b.std() > 0 else float("nan")
    score = min(correlations[60], correlations[120]) - max(correlations[30], correlations[90], correlations[150])
    return Gridness(float(score), spacing, inner, outer, correlations)
