"""The three lattice-flow decoders on known shifts of a real lattice."""

import numpy as np
import pytest

from services.gridcells.decoders import DECODERS, _spectral_norm, decode_paper, decode_paper_bruteforce
from services.gridcells.network import GridCellError, GridNetwork, NetworkParams


@pytest.fixture(scope="module")
def lattice() -> np.ndarray:
    """A torus-periodic lattice field (settled, then 20 periodic zero-velocity frames)."""
    network = GridNetwork()
    for _ in range(20):
        network.run((0.0, 0.0))
    return network.field.astype(np.float64)


@pytest.fixture(scope="module")
def moving_pair() -> tuple[np.ndarray, np.ndarray]:
    """Two consecutive fields of a moving 64×64 lattice (not an exact circular shift of each
    other; 64×64 keeps the brute-force loop's 361 SVDs cheap)."""
    network = GridNetwork(NetworkParams(n=64), dtype=np.float64)
    previous = network.run((0.06, 0.03))
    return previous, network.run((0.06, 0.03))


def fourier_shift(field: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """The band-limited translation of ``field`` by (dx columns, dy rows)."""
    n = field.shape[0]
    k = np.fft.fftfreq(n)
    phase = np.exp(-2j * np.pi * (k[:, None] * dy + k[None, :] * dx))
    return np.real(np.fft.ifft2(np.fft.fft2(field) * phase))


@pytest.mark.parametrize("name", sorted(DECODERS))
@pytest.mark.parametrize("dx, dy", [(0, 0), (3, -5), (-7, 2), (9, -9), (-1, 8)])
def test_decoder_recovers_a_circular_shift(lattice, name, dx, dy):
    shifted = np.roll(lattice, (dy, dx), axis=(0, 1))
    found = DECODERS[name](lattice, shifted)
    assert found == pytest.approx((dx, dy), abs=0.02)


def test_subpixel_recovers_a_fractional_shift_better_than_integer_decoders(lattice):
    truth = np.array([2.3, -1.6])
    shifted = fourier_shift(lattice, *truth)
    errors = {name: np.hypot(*(np.array(decoder(lattice, shifted)) - truth)) for name, decoder in DECODERS.items()}
    assert errors["subpixel"] < 0.05, errors
    assert errors["paper"] > 0.3 and errors["fft"] > 0.3, errors  # the nearest integer shift is 0.5 away


def test_paper_decoder_equals_the_authors_brute_force_loop(moving_pair):
    previous, field = moving_pair
    assert decode_paper(previous, field) == decode_paper_bruteforce(previous, field)
    # And on a pair whose best shift is zero (ties and flat minima are the hard case).
    assert decode_paper(field, field) == (0.0, 0.0)


def test_spectral_norm_equals_lapack(lattice, moving_pair):
    rng = np.random.default_rng(1)
    matrices = [np.roll(lattice, (3, -2), axis=(0, 1)) - lattice, moving_pair[1] - moving_pair[0], rng.normal(size=(40, 40))]
    for matrix in matrices:
        assert _spectral_norm(matrix) == pytest.approx(np.linalg.norm(matrix, 2), rel=1e-13)
    assert _spectral_norm(np.zeros((16, 16))) == 0.0


def test_paper_decoder_keeps_the_first_minimum_in_loop_order():
    # Columns periodic with period 4, rows constant: every dx ≡ 1 (mod 4) and every dy match
    # exactly; the authors' loop (dx outer, dy inner, from -search) keeps the first of them.
    field = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (16, 4))
    shifted = np.roll(field, 1, axis=1)
    assert decode_paper(field, shifted, search=7) == decode_paper_bruteforce(field, shifted, search=7) == (-7.0, -7.0)


def test_decoders_reject_mismatched_fields():
    with pytest.raises(GridCellError, match="square fields"):
        DECODERS["fft"](np.zeros((8, 8)), np.zeros((8, 6)))
    with pytest.raises(GridCellError, match="search range"):
        DECODERS["subpixel"](np.zeros((8, 8)), np.zeros((8, 8)), search=4)
