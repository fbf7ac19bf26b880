"""The grid-cell network: settling, the lattice it forms, its flow under a constant velocity,
and the fast sub-lattice step against the authors' full-sheet formulation."""

import numpy as np
import pytest

from services.benchmarks.gridcells import FullSheetNetwork
from services.common.errors import ConfigError
from services.gridcells.decoders import decode_subpixel
from services.gridcells.integrator import LATTICE_RATE
from services.gridcells.network import (
    GridCellError,
    GridNetwork,
    NetworkParams,
    merge,
    settled_state,
    split,
)


def lattice_peaks(field: np.ndarray, count: int = 3) -> list[tuple[float, float]]:
    """(period in neurons, angle in degrees) of the ``count`` strongest wavevectors of the
    lattice, one per ± pair, frequencies above 0.12 cycles/neuron (the 2×2 pattern) ignored."""
    n = field.shape[0]
    power = np.abs(np.fft.fft2(field - field.mean())) ** 2
    k = np.fft.fftfreq(n) * n
    ky, kx = np.meshgrid(k, k, indexing="ij")
    power[np.hypot(kx, ky) > 0.12 * n] = 0
    power[(ky < 0) | ((ky == 0) & (kx < 0))] = 0  # one of each conjugate pair
    best = np.argsort(power.ravel())[::-1][:count]
    return [(n / np.hypot(kx.flat[i], ky.flat[i]), np.degrees(np.arctan2(ky.flat[i], kx.flat[i])) % 180) for i in best]


def test_settling_matches_the_authors_octave_state(shared_data):
    reference = np.loadtxt(shared_data / "seed_reference" / "settled_state_128x128.csv", delimiter=",")
    state, _ = settled_state(NetworkParams())
    # The CSV holds 10 significant digits: agreement to that precision.
    assert np.max(np.abs(state - reference)) < 1e-9 * np.max(reference)
    assert not state.flags.writeable


def test_settled_lattice_has_the_expected_period():
    state, _ = settled_state(NetworkParams())
    period, _ = lattice_peaks(state, 1)[0]
    assert 24 <= period <= 30  # the authors' code forms a lattice of ~25-29 neurons, not λ = 18


def test_lattice_is_hexagonal_once_periodic():
    network = GridNetwork()
    for _ in range(20):  # the envelope-settled lattice re-forms on the torus within ~20 frames
        network.run((0.0, 0.0))
    peaks = lattice_peaks(network.field, 3)
    assert all(22 <= period <= 30 for period, _ in peaks), peaks
    angles = sorted(angle for _, angle in peaks)
    gaps = np.diff(angles + [angles[0] + 180])
    assert np.all(np.abs(gaps - 60) < 8), peaks


def test_sub_lattice_step_equals_the_full_sheet_step():
    params = NetworkParams(n=32, steps_per_frame=5, settle_steps=60, envelope_steps=40)
    network = GridNetwork(params, dtype=np.float64)
    reference = FullSheetNetwork(params, network.state)  # the authors' formulation
    field_ref = reference.run((0.03, -0.02))
    field = network.run((0.03, -0.02))
    assert np.allclose(network.state, reference.r, atol=1e-12)
    assert np.allclose(field, field_ref, atol=1e-12)


def test_split_and_merge_are_inverse():
    sheet = np.arange(36.0).reshape(6, 6)
    sub = split(sheet)
    assert sub.shape == (4, 3, 3)
    assert sub[3, 0, 0] == sheet[1, 1]  # (odd, odd) 0-based parity = right
    assert np.array_equal(merge(sub), sheet)


@pytest.mark.parametrize("velocity, direction", [((0.05, 0.0), (1, 0)), ((0.0, 0.05), (0, -1)), ((-0.035, -0.035), (-1, 1))])
def test_constant_velocity_moves_the_lattice_at_a_constant_rate(velocity, direction):
    network = GridNetwork()
    previous = network.run(velocity)
    shifts = []
    for _ in range(4):
        field = network.run(velocity)
        shifts.append(decode_subpixel(previous, field))
        previous = field
    shifts = np.array(shifts)
    expected = LATTICE_RATE * network.params.alpha * network.params.steps_per_frame * np.hypot(*velocity)
    # Columns grow with world +x, rows shrink with world +y.
    unit = np.array(direction, dtype=float) / np.hypot(*direction)
    assert np.allclose(shifts @ unit, expected, rtol=0.05), shifts
    assert np.all(np.abs(shifts @ np.array([-unit[1], unit[0]])) < 0.1 * expected), shifts
    assert np.ptp(shifts, axis=0).max() < 0.1 * expected  # constant rate


def test_float32_network_follows_float64():
    fields = [GridNetwork(dtype=dtype).run((0.04, 0.02)) for dtype in (np.float32, np.float64)]
    assert np.max(np.abs(fields[0] - fields[1])) < 1e-3 * np.max(fields[1])


def test_non_finite_velocity_is_an_error():
    network = GridNetwork(NetworkParams(n=16, settle_steps=0), settle=False)
    with pytest.raises(GridCellError, match="not finite"):
        network.run((float("nan"), 0.0))
    with pytest.raises(GridCellError, match="shape"):
        network.state = np.zeros((8, 8))


def test_bad_parameters_are_config_errors():
    with pytest.raises(ConfigError, match="even"):
        NetworkParams(n=31)
    with pytest.raises(ConfigError, match="tau"):
        NetworkParams(tau=0.0)


def _backends():
    from services.gridcells.network import fft_backend

    return ["scipy"] + (["fftw"] if fft_backend() == "fftw" else [])


@pytest.mark.parametrize("backend", _backends())
@pytest.mark.parametrize("lam", [18.0, 18.0 / 1.4, 18.0 / 1.96])
def test_fast_stack_follows_the_float64_network(backend, lam):
    """NetworkStack (float32, band-limited rank-one product, input on the zero-frequency bin)
    runs the same dynamics as GridNetwork to float32 precision: on the rank-one path (λ < 18
    at n = 64) and on the full 4×4 product (λ = 18 at n = 64: the small sheet truncates the
    kernel, so the rank-one form does not hold)."""
    from services.gridcells.network import NetworkStack

    params = NetworkParams(n=64, lam=lam)
    reference = GridNetwork(params, dtype=np.float64)
    stack = NetworkStack(params, backend=backend)
    for velocity in ((0.04, 0.02), (-0.03, 0.05), (0.0, 0.0)):
        expected = reference.run(velocity)
        field = stack.run(velocity)[0]
    assert np.max(np.abs(field - expected)) < 2e-5 * np.max(expected)
    assert np.max(np.abs(stack.state[0] - reference.state)) < 2e-5 * np.max(reference.state)


def test_stack_modules_run_side_by_side_with_their_own_velocities():
    from services.gridcells.network import NetworkStack

    modules = (NetworkParams(n=32, settle_steps=60, envelope_steps=40), NetworkParams(n=32, lam=14.0, alpha=1.5, settle_steps=60, envelope_steps=40))
    stack = NetworkStack(modules)
    singles = [NetworkStack(p) for p in modules]
    velocities = np.array([[0.03, -0.01], [-0.02, 0.04]])
    fields = stack.run(velocities)
    for k, single in enumerate(singles):
        assert np.allclose(fields[k], single.run(velocities[k])[0], atol=1e-6)
    with pytest.raises(GridCellError, match="shape"):
        stack.run(np.zeros((3, 2)))
    with pytest.raises(ConfigError, match="share n"):
        NetworkStack((NetworkParams(n=32), NetworkParams(n=64)))
