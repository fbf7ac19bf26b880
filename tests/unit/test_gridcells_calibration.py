"""The calibrated lattice flow: the table's inverse, its cache, a real (small) measurement, the
decoder built on it, step from the lattice, grid modules and the grid code."""

import cmath
import math

import numpy as np
import pytest

from services.gridcells.calibration import (
    PACKAGED,
    CalibrationGrid,
    FlowTable,
    LagInverter,
    cache_key,
    check_velocities,
    flow_table,
    flow_table_path,
    lag_components,
    measure_flow,
)
from services.gridcells.decoders import decode_subpixel
from services.gridcells.gridcode import GridCode
from services.gridcells.integrator import (
    DECODER_NAMES,
    GridCellError,
    GridCellIntegrator,
    module_params,
)
from services.gridcells.network import NetworkParams, NetworkStack

# A 64×64 network and a coarse grid keep a real measurement under a few seconds.
SMALL = NetworkParams(n=64)
SMALL_GRID = CalibrationGrid(directions=12, axis_span_deg=0, drives=(0.03, 0.1, 0.2), settle_frames=10, min_frames=4,
                             check_frames=40, warm_frames=60)


@pytest.fixture(scope="module")
def small_table() -> FlowTable:
    return measure_flow(SMALL, SMALL_GRID)


def synthetic_table(params=NetworkParams()) -> FlowTable:
    """A made-up table: a gain of 37 that turns the flow by 0.3°·sin 2θ and falls with speed."""
    angles = np.radians(np.arange(0, 360, 10.0))
    speeds = np.array([0.002, 0.02, 0.08, 0.15])
    gain = 37.0 * (1 - 0.5 * speeds[None, :] ** 2) * np.exp(1j * np.radians(0.3) * np.sin(2 * angles)[:, None])
    zeros = np.zeros((params.n, params.n), dtype=np.float32)
    return FlowTable(params, 9, angles, speeds, gain, np.zeros(gain.shape), 0.02, 1e-4, zeros, zeros)


@pytest.mark.parametrize("velocity", [0.05 + 0.02j, -0.1j, -0.001 + 0.0003j, 0.12 * cmath.exp(1j * 2.1)])
def test_invert_undoes_the_tabulated_flow(velocity):
    table = synthetic_table()
    flow = table.flow(velocity)
    assert abs(cmath.phase(flow / velocity)) > 0 or abs(math.sin(2 * cmath.phase(velocity))) < 1e-9
    assert table.invert(flow) == pytest.approx(velocity, abs=1e-9 * abs(velocity))
    assert table.invert(0j) == 0j


def test_lag_inverter_recovers_the_lagged_flow_and_conserves_displacement():
    """The lag model flow_k = F_k + c·(F_{k−1} − F_k) inverted exactly on a path that turns and
    changes speed; and on any sequence of flows (noise) the own flows sum to the decoded ones
    plus c·F_last: the lag correction adds no drift (an along/across split of the change did)."""
    table = synthetic_table()
    rng = np.random.default_rng(3)
    k = np.arange(200)
    velocities = (0.05 + 0.04 * np.sin(k / 7.0)) * np.exp(1j * np.cumsum(rng.normal(0, 0.2, k.size)))
    own = np.array([table.flow(v) for v in velocities])
    lagged = own + table.lag * (np.r_[0, own[:-1]] - own)
    inverter = LagInverter(table)
    decoded = np.array([inverter(w) for w in lagged])
    assert np.allclose(decoded, velocities, rtol=0, atol=1e-9 * np.abs(velocities).max())
    noisy = lagged + rng.normal(0, 0.3, k.size) + 1j * rng.normal(0, 0.3, k.size)
    inverter = LagInverter(table)
    corrected = []
    for w in noisy:
        inverter(w)
        corrected.append(inverter.previous_flow)
    assert sum(corrected) - noisy.sum() == pytest.approx(table.lag * corrected[-1], abs=1e-9)


def test_lag_components_split_a_change_of_speed_from_a_turn():
    """Flows that carry 3 % of each change of speed and 2 % of each turn a frame late give
    back those two fractions."""
    table = synthetic_table()
    velocities = check_velocities(300, 0.075)
    own = np.array([table.flow(v) for v in velocities])
    direction = own[1:] / np.maximum(np.abs(own[1:]), 1e-30)  # (the sequence stops once: no direction there)
    change = (own[:-1] - own[1:]) * np.conj(direction)
    lagged = np.r_[own[0], own[1:] + direction * (0.03 * change.real + 0.02j * change.imag)]
    assert lag_components(table, velocities, lagged) == pytest.approx((0.03, 0.02), abs=1e-9)


def test_save_load_round_trip_and_the_cache(tmp_path, small_table):
    path = small_table.save(tmp_path / "table.npz")
    loaded = FlowTable.load(path)
    assert np.array_equal(loaded.gain, small_table.gain) and loaded.params == small_table.params
    assert (loaded.lag, loaded.noise, loaded.search) == (small_table.lag, small_table.noise, small_table.search)
    # flow_table writes a measurement to the cache and reads it back the next time.
    grid = CalibrationGrid(directions=4, axis_span_deg=0, drives=(0.05, 0.1), settle_frames=1, min_frames=2, check_frames=0, warm_frames=2)
    first = flow_table(SMALL, grid, cache=tmp_path)
    assert flow_table_path(tmp_path, SMALL, grid).exists()
    again = flow_table(SMALL, grid, cache=tmp_path)
    assert np.array_equal(first.gain, again.gain)
    # Any parameter that shapes the table changes its key.
    assert cache_key(SMALL, grid, None) != cache_key(NetworkParams(n=64, alpha=1.9), grid, None)
    assert cache_key(SMALL, grid, None) != cache_key(SMALL, CalibrationGrid(), None)


def test_measured_table_of_a_real_network(small_table):
    table = small_table
    half = len(table.angles) // 2
    assert np.allclose(table.angles[half:], table.angles[:half] + math.pi)
    assert np.array_equal(table.gain[half:], table.gain[:half])  # v → −v symmetry
    # Tens of neurons per network unit (38 at n = 128; the 64² lattice, period ~21, flows
    # faster), turned by a few degrees at most.
    assert np.all((30 < np.abs(table.gain)) & (np.abs(table.gain) < 60)), np.abs(table.gain)
    assert np.all(np.abs(np.degrees(np.angle(table.gain))) < 3.0)
    assert abs(table.lag) < 0.1  # 2 % at n = 128; 40 frames of the small sheet say less
    assert table.noise > 0 and 2 <= table.search <= 9
    assert table.warm_state.shape == (64, 64)


def test_calibrated_decoder_takes_out_the_direction_error(small_table):
    """At a tabulated direction and speed the decoded direction is the input's, where the raw
    shift is off by the lattice's own error."""
    table = small_table
    velocity = table.speeds[1] * cmath.exp(1j * table.angles[1])
    network = NetworkStack(SMALL, settle=False)
    network.state = table.warm_state[None]
    network.set_field(table.warm_field[None])
    previous = network.fields[0]
    flows = []
    for frame in range(20):  # as the table was measured: settled for 10 frames, then averaged
        field = network.run((velocity.real, velocity.imag))[0]
        dx, dy = decode_subpixel(previous, field, table.search)
        previous = field
        if frame >= 10:
            flows.append(complex(dx, -dy))
    raw = abs(cmath.phase(np.mean(flows) / velocity))
    calibrated = abs(cmath.phase(table.invert(np.mean(flows)) / velocity))
    assert calibrated < 0.35 * raw, (raw, calibrated)  # (the rest: the lattice remembers its history)


def test_lattice_step_integrates_a_straight_walk(small_table):
    heading = small_table.angles[1]
    integrator = GridCellIntegrator(SMALL, decoder="calibrated", velocity_scale=2.0, heading0=heading, step="lattice",
                                    calibration_cache=False, calibration_grid=SMALL_GRID)
    speed = small_table.speeds[1] / 2.0  # metres per frame at 2 units per metre
    for _ in range(15):
        step = integrator.step(speed, 0.0, 0.0)
        assert not step.saturated
    x, y = integrator.pose.x, integrator.pose.y
    assert math.hypot(x, y) == pytest.approx(15 * speed, rel=0.01)
    assert abs(math.atan2(y, x) - heading) < math.radians(0.5)
    # Driven far beyond its table, the lattice cannot say how far it went: the frame is
    # flagged and its length is the input's.
    fast = 3 * small_table.max_speed / 2.0
    step = integrator.step(fast, 0.0, 0.0)
    assert step.saturated and step.step_length == pytest.approx(fast, rel=1e-12)


def test_modules_combine_and_decode_a_position():
    params = NetworkParams(n=64)
    integrator = GridCellIntegrator(params, decoder="calibrated", velocity_scale=2.0, modules=2, step="lattice",
                                    calibration_cache=False, calibration_grid=SMALL_GRID)
    assert [t.params.alpha for t in integrator.tables] == pytest.approx([2.0, 2.0 / 1.4])
    assert integrator.weights.sum() == pytest.approx(1.0) and np.all(integrator.weights > 0)
    for _ in range(20):
        integrator.step(0.03, 0.0, 0.01)
    position = complex(integrator.pose.x, integrator.pose.y)
    code = GridCode(integrator.tables, integrator.velocity_scale, integrator.rotations)
    decoded = code.decode(integrator.network.fields, prior=position + 0.3 * code.spacings.min())
    # The phases bring a prior off by 0.3 spacings back to the integrated position.
    assert abs(decoded - position) < 0.1 * code.spacings.min(), (decoded, position, code.spacings)


def test_options_need_the_calibrated_decoder():
    with pytest.raises(GridCellError, match="calibrated"):
        GridCellIntegrator(decoder="subpixel", step="lattice")
    with pytest.raises(GridCellError, match="calibrated"):
        GridCellIntegrator(decoder="fft", modules=2)
    with pytest.raises(GridCellError, match="modules"):
        module_params(NetworkParams(), 5)
    with pytest.raises(GridCellError, match="heading model"):
        GridCellIntegrator(heading="compass")


def test_shipped_tables_match_the_default_modules():
    """The tables shipped with the package are found under the keys the code computes (a
    change of parameters or of the measurement without `gridslam calibrate` fails here)."""
    for params in module_params(NetworkParams(), 4):
        path = flow_table_path(PACKAGED, params)
        assert path.exists(), f"{path.name} missing: run `gridslam calibrate --modules 4 --out {PACKAGED}`"
        assert FlowTable.load(path).params == params


def test_cli_decoder_list_matches_the_integrator():
    import argparse

    from services.cli import integrate

    parser = argparse.ArgumentParser()
    integrate.register(parser.add_subparsers())
    command = parser._subparsers._group_actions[0].choices["integrate"]
    decoder = next(action for action in command._actions if "--decoder" in action.option_strings)
    assert tuple(decoder.choices) == tuple(DECODER_NAMES)
