"""The paper's simulation: the random walk in the circle, firing maps, the gridness score
(Sargolini et al. 2006) on synthetic maps, and a short run of `simulate`."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import ndimage

from services.offline.integration import simulate
from services.gridcells.simulation import WalkParams, autocorrelogram, firing_map, gridness, random_walk


def _plane_waves(shape, period, angles_deg, phase=0.0):
    """Sum of cosine gratings of one period along the given directions."""
    y, x = np.indices(shape, dtype=float)
    k = 2 * math.pi / period
    return sum(np.cos(k * (x * math.cos(math.radians(a)) + y * math.sin(math.radians(a)))) + phase for a in angles_deg)


def test_gridness_of_a_hexagonal_map_is_high():
    hexagonal = _plane_waves((60, 60), 12.0, (10, 70, 130))
    score = gridness(hexagonal)
    assert score.score > 1.0
    assert score.correlations[60] > 0.8 and score.correlations[120] > 0.8
    assert score.spacing_bins == pytest.approx(12 * 2 / math.sqrt(3), rel=0.2)  # peak distance of the grating sum


def test_gridness_of_square_and_random_maps_is_low():
    square = _plane_waves((60, 60), 12.0, (0, 90))
    assert gridness(square).score < -0.5  # 90° symmetry: r90 high, r60 low
    # Irregular maps (white noise, and blobs: noise smoothed over 3 bins) score near zero on
    # average; single maps scatter by a few tenths, far below a hexagonal map's > 1.
    scores = []
    for seed in range(8):
        noise = np.random.default_rng(seed).normal(size=(60, 60))
        scores += [gridness(noise).score, gridness(ndimage.gaussian_filter(noise, 3)).score]
    assert max(scores) < 0.6
    assert np.mean(scores) < 0.2


def test_gridness_tolerates_unvisited_bins():
    hexagonal = _plane_waves((60, 60), 12.0, (25, 85, 145))
    holes = np.random.default_rng(2).random(hexagonal.shape) < 0.25
    hexagonal[holes] = np.nan
    assert gridness(hexagonal).score > 1.0


def test_autocorrelogram_is_one_at_zero_lag_and_symmetric():
    rate = np.random.default_rng(3).random((20, 25))
    rate[3, 4] = np.nan
    ac = autocorrelogram(rate)
    assert ac.shape == (39, 49)
    assert ac[19, 24] == pytest.approx(1.0)
    np.testing.assert_allclose(ac, ac[::-1, ::-1], equal_nan=True, atol=1e-9)


def test_random_walk_stays_in_the_circle_under_the_speed_limit():
    params = WalkParams()
    walk = random_walk(5000, seed=7, params=params)
    assert len(walk) == 5000
    assert np.hypot(*walk.positions.T).max() <= params.radius_m + 1e-9
    speeds = np.hypot(*np.diff(walk.positions, axis=0).T) / params.frame_period_s
    assert speeds.max() <= params.max_speed_m_s + 1e-9
    assert 0.5 < speeds.mean() < 1.5  # moves, and not always at the limit
    np.testing.assert_array_equal(walk.positions, random_walk(5000, seed=7).positions)
    assert not np.array_equal(walk.positions, random_walk(5000, seed=8).positions)
    # A longer walk with the same seed continues this one (the firing-map run).
    np.testing.assert_array_equal(random_walk(6000, seed=7).positions[:5000], walk.positions)


def test_walk_increments_rebuild_the_walk():
    """Body increments in the integrators' convention (turn, then move forward)."""
    walk = random_walk(800, seed=4)
    increments = walk.body_increments()
    heading = walk.heading[0] + np.cumsum(increments[:, 2])
    steps = increments[:, :1] * np.column_stack([np.cos(heading), np.sin(heading)])
    np.testing.assert_allclose(walk.positions[0] + np.cumsum(steps, axis=0), walk.positions, atol=1e-9)


def test_firing_map_of_an_ideal_grid_cell_is_hexagonal():
    """A cell that fires on a hexagonal lattice of 0.5 m, sampled along a long walk, gives a
    map of high gridness; the same walk with a cell firing in stripes gives a low one."""
    walk = random_walk(60000, seed=5)
    x, y = walk.positions.T
    k = 2 * math.pi / (0.5 * math.sqrt(3) / 2)

    def grating(angles):
        return sum(np.cos(k * (x * math.cos(math.radians(a)) + y * math.sin(math.radians(a))) ) for a in angles)

    grid_cell = np.maximum(grating((0, 60, 120)), 0)
    stripes = np.maximum(grating((30,)), 0)
    hexagonal = firing_map(walk.positions, grid_cell, extent_m=2.0, bin_m=0.05)
    assert hexagonal.rate.shape == (80, 80)
    assert np.isnan(hexagonal.rate[0, 0])  # a corner of the square outside the circle
    assert gridness(hexagonal.rate).score > 0.8
    assert gridness(firing_map(walk.positions, stripes, extent_m=2.0).rate).score < 0.3


def test_short_simulation_writes_its_results(tmp_path):
    """A short run through the real network: dead reckoning of noise-free odometry is exact,
    the subpixel decoder stays within a few per cent, and every file is written."""
    result = simulate(n_frames=60, seed=1, decoders=("subpixel",), firing_frames=0, out=tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["deadreckoning"]["endpoint_error_m"] < 1e-9
    assert metrics["subpixel"]["mean_error_pct"] < 3.0
    assert metrics["subpixel"]["saturations"] == 0
    assert result.velocity_scale == pytest.approx(metrics["velocity_scale"])
    for name in ("groundtruth.tum", "deadreckoning.tum", "trajectory_subpixel.tum", "drift.png", "trajectories.png", "config.json"):
        assert (tmp_path / name).is_file(), name
    rows = [line for line in (tmp_path / "trajectory_subpixel.tum").read_text().splitlines() if not line.startswith("#")]
    assert len(rows) == 60
