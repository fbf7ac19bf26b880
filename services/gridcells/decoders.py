"""Reading the flow of the activity lattice between two frames.

Every decoder takes the rectified fields of the previous and the current frame and returns
the shift (dx, dy) in lattice columns and rows such that

    np.roll(prev_field, (dy, dx), axis=(0, 1)) ≈ field

(the authors' ``circshift(fr_old, [shift_y, shift_x])``). The network moves its lattice toward
larger columns for world +x and toward smaller rows for world +y (see network.py), so the
direction of travel in the world is (dx, −dy) (paper eq. 5). Shifts are searched in
[−search, search] on each axis.

- ``paper``: the authors' exhaustive search with MATLAB's ``norm`` of a matrix, which is the
  spectral norm (largest singular value): dx outer, dy inner, from −search to search, the first
  strict minimum is kept. The same result without 361 SVDs: a batched power iteration gives a
  lower bound of every shift's norm; only shifts whose lower bound does not exceed the exact
  norm of the best candidate can be the minimum, and only those get an exact norm (usually
  one per frame). decode_paper_bruteforce is the loop as written, for tests and benchmarks.
- ``fft``: the same search with the Frobenius norm. Circular shifts keep ‖prev‖, so the argmin
  of ‖roll(prev, s) − field‖_F is the argmax of the cross-correlation, all shifts at once by FFT.
- ``subpixel``: both fields low-passed (the lattice period is ~27 neurons; the stationary 2×2
  input pattern sits at 0.5 cycles/neuron and biases integer shifts toward even values), the
  integer peak of the cross-correlation, then Newton steps on its band-limited (Fourier)
  interpolant to a fraction of a neuron.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.fft

from services.gridcells.network import GridCellError

# Low-pass of the subpixel decoder: a Gaussian weight exp(−|k|²/(2σ²)) on the cross-power
# spectrum, σ in cycles per neuron. It keeps the lattice fundamental (~1/27 ≈ 0.037) and its
# second harmonic, and removes the 2×2 input pattern (0.5) and the neuron-scale detail.
LOWPASS_SIGMA = 0.06
# Bins beyond this radius (cycles/neuron) carry < 1e-7 of the weight: left out of the refinement.
_REFINE_RADIUS = 0.34
_NEWTON_STEPS = 4
# decode_paper: power iterations for all shifts, then for the shifts still in the running.
_PAPER_ITERATIONS = 2
_PAPER_REFINE_ITERATIONS = 12
_NORM_MAX_ITERATIONS = 300


def _check(prev_field: np.ndarray, field: np.ndarray, search: int) -> tuple[np.ndarray, np.ndarray]:
    prev_field = np.asarray(prev_field)
    field = np.asarray(field)
    if prev_field.ndim != 2 or prev_field.shape != field.shape or prev_field.shape[0] != prev_field.shape[1]:
        raise GridCellError(f"decoder needs two square fields of equal shape, got {prev_field.shape} and {field.shape}")
    if not 0 <= search < prev_field.shape[0] // 2:
        raise GridCellError(f"shift search range {search} must be in [0, n/2) for n={prev_field.shape[0]}")
    return prev_field, field


def _window(surface: np.ndarray, search: int) -> np.ndarray:
    """Values of an n×n circular surface indexed [sy, sx] as a (2S+1)² array indexed
    [dx + S, dy + S]: dx outer, dy inner, the authors' loop order."""
    offsets = np.arange(-search, search + 1)
    return surface[np.ix_(offsets, offsets)].T


def _first_argmax(values: np.ndarray, search: int) -> tuple[int, int]:
    # np.argmax returns the first maximum in C order, i.e. dx outer, dy inner.
    ix, iy = np.unravel_index(int(np.argmax(values)), values.shape)
    return int(ix) - search, int(iy) - search


def _cross_power(prev_field: np.ndarray, field: np.ndarray) -> np.ndarray:
    """conj(F[prev])·F[field] on the rfft2 grid: its inverse transform at [sy, sx] is the
    cross-correlation Σ roll(prev, (sy, sx))·field."""
    return np.conj(scipy.fft.rfft2(prev_field.astype(np.float64))) * scipy.fft.rfft2(field.astype(np.float64))


def decode_fft(prev_field, field, search: int = 9) -> tuple[float, float]:
    """Integer shift minimising the Frobenius distance ‖roll(prev, (dy, dx)) − field‖_F,
    first minimum in the authors' loop order."""
    prev_field, field = _check(prev_field, field, search)
    corr = scipy.fft.irfft2(_cross_power(prev_field, field), s=field.shape)
    dx, dy = _first_argmax(_window(corr, search), search)
    return float(dx), float(dy)


@functools.lru_cache(maxsize=8)
def _subpixel_grid(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For an n×n rfft2 grid: the low-pass weight, and for the bins kept in the refinement
    their mask, angular frequencies 2πkx, 2πky (rad/neuron) and multiplicity (2 for the rfft
    columns that stand for a conjugate pair). Read-only."""
    ky = np.fft.fftfreq(n)[:, None] * np.ones((1, n // 2 + 1))
    kx = np.fft.rfftfreq(n)[None, :] * np.ones((n, 1))
    weight = np.exp(-(kx**2 + ky**2) / (2 * LOWPASS_SIGMA**2))
    keep = kx**2 + ky**2 <= _REFINE_RADIUS**2
    multiplicity = np.where((kx == 0) | (kx == 0.5), 1.0, 2.0)[keep]
    arrays = (weight, keep, 2 * np.pi * kx[keep], 2 * np.pi * ky[keep], multiplicity)
    for array in arrays:
        array.setflags(write=False)
    return arrays


def decode_subpixel(prev_field, field, search: int = 9) -> tuple[float, float]:
    """Shift to a fraction of a neuron: the low-passed cross-correlation, its integer peak in
    the search window, then Newton steps on its band-limited interpolant
    c(s) = Σ_k m_k·Re(X_k·exp(2πi k·s)) (X the weighted cross-power spectrum)."""
    prev_field, field = _check(prev_field, field, search)
    return _refine(_cross_power(prev_field, field), field.shape[0], search)


@functools.lru_cache(maxsize=16)
def _window_index(n: int, search: int) -> np.ndarray:
    """Flat indices into an n×n surface of _window's (2S+1)² array (dx outer, dy inner)."""
    offsets = np.arange(-search, search + 1) % n
    index = (offsets[None, :] * n + offsets[:, None])  # [dx, dy] → surface[dy, dx]
    index.setflags(write=False)
    return index


def _refine(cross: np.ndarray, n: int, search: int) -> tuple[float, float]:
    """decode_subpixel's peak and Newton refinement from the (unweighted) cross-power."""
    weight, keep, kx, ky, multiplicity = _subpixel_grid(n)
    cross = cross * weight
    corr = scipy.fft.irfft2(cross, s=(n, n))
    dx, dy = _first_argmax(corr.ravel()[_window_index(n, search)], search)
    spectrum = cross[keep] * multiplicity
    s0, s1 = float(dx), float(dy)
    kxx, kxy, kyy = _second_moments(n)
    for _ in range(_NEWTON_STEPS):
        rotated = spectrum * np.exp(1j * (kx * s0 + ky * s1))
        im, re = rotated.imag, rotated.real
        g0, g1 = -float(kx @ im), -float(ky @ im)
        h00, h01, h11 = -float(kxx @ re), -float(kxy @ re), -float(kyy @ re)
        det = h00 * h11 - h01 * h01
        if not (det > 0 and h00 < 0):
            break  # not at a maximum: keep the integer peak (or the last good estimate)
        step0, step1 = -(h11 * g0 - h01 * g1) / det, -(h00 * g1 - h01 * g0) / det
        if max(abs(step0), abs(step1)) > 1.0:
            break  # the interpolant's peak is not near this integer peak
        s0, s1 = s0 + step0, s1 + step1
        if max(abs(step0), abs(step1)) < 1e-6:
            break
    return s0, s1


@functools.lru_cache(maxsize=8)
def _second_moments(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    _, _, kx, ky, _ = _subpixel_grid(n)
    arrays = (kx * kx, kx * ky, ky * ky)
    for array in arrays:
        array.setflags(write=False)
    return arrays


class SubpixelReader:
    """decode_subpixel frame after frame: each field is transformed once (its spectrum is the
    next frame's previous one). Same result as decode_subpixel(previous, field, search)."""

    def __init__(self, field: np.ndarray, search: int = 9):
        field = np.asarray(field)
        _check(field, field, search)
        self.n, self.search = field.shape[0], search
        self._previous = scipy.fft.rfft2(field.astype(np.float64))

    def __call__(self, field: np.ndarray) -> tuple[float, float]:
        """The shift from the previous field to ``field``, which becomes the previous one."""
        spectrum = scipy.fft.rfft2(np.asarray(field, dtype=np.float64))
        cross = np.conj(self._previous) * spectrum
        self._previous = spectrum
        return _refine(cross, self.n, self.search)

    def reset(self, field: np.ndarray) -> None:
        self._previous = scipy.fft.rfft2(np.asarray(field, dtype=np.float64))


def _rows_per_product(n: int) -> int:
    """Rows per block so a (rows×n)·(n×n) product stays on one OpenBLAS thread (it threads
    above m·n·k = 2¹⁸). Its threads stall badly when the cores are busy with other processes:
    a 128×128 LAPACK SVD then takes 10-900 ms instead of 0.9 ms."""
    return max(1, 2**18 // (n * n))


def _blocked_product(rows: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """rows @ matrix as a batch of single-threaded products (see _rows_per_product)."""
    count, n = rows.shape
    block = _rows_per_product(n)
    padded = -count % block
    if padded:
        rows = np.concatenate([rows, np.zeros((padded, n), dtype=rows.dtype)])
    return (rows.reshape(-1, block, n) @ matrix).reshape(-1, matrix.shape[1])[:count]


def _spectral_norm(matrix: np.ndarray) -> float:
    """MATLAB/Octave ``norm(M)`` of a matrix: its largest singular value.

    Block subspace iteration on MᵀM (16 vectors, Rayleigh-Ritz) to convergence in double
    precision; it agrees with LAPACK's SVD to ~1e-15 relative (tested), in about 15
    single-threaded iterations. LAPACK is the fallback if it does not converge."""
    gram = _blocked_product(matrix.T.copy(), matrix)
    n = gram.shape[0]
    width = min(16, n)
    # Start from the Gram matrix's largest columns: they lie near the top singular vectors.
    start = np.argsort(np.einsum("ij,ij->j", gram, gram))[-width:]
    basis, _ = np.linalg.qr(gram[:, start])
    previous = 0.0
    for _ in range(_NORM_MAX_ITERATIONS):
        image = _blocked_product(gram, basis)
        theta = float(np.linalg.eigvalsh(basis.T @ image)[-1])  # the largest Ritz value
        if theta <= 0.0:
            return 0.0
        if theta - previous <= 1e-15 * theta:
            return float(np.sqrt(theta))
        previous = theta
        basis, _ = np.linalg.qr(image)
    return float(np.linalg.norm(matrix, 2))


class _ShiftNorms:
    """Lower bounds of ‖D_s‖₂, D_s = roll(A, (sy, sx)) − B, for many shifts s at once, by
    power iteration on D_sᵀD_s: ‖D_s v‖ ≤ ‖D_s‖₂ for every unit v.

    Each shift's vector is a row of V (S×n). With D_s v = roll(A·roll(v, −sx), sy) − B·v and
    D_sᵀu = roll(Aᵀ·roll(u, −sy), sx) − Bᵀ·u, one iteration for all shifts is four S×n by
    n×n products (single-threaded blocks, _rows_per_product) and four gathers."""

    def __init__(self, prev_field: np.ndarray, field: np.ndarray, sx: np.ndarray, sy: np.ndarray):
        self.n = field.shape[0]
        # Row vectors: (A·v)ᵀ = vᵀ·Aᵀ and (Aᵀ·u)ᵀ = uᵀ·A.
        self.a_t, self.b_t, self.a, self.b = prev_field.T.copy(), field.T.copy(), prev_field, field
        self.sx, self.sy = sx, sy
        self.start = np.full(self.n, 1.0 / np.sqrt(self.n))
        self.vectors = np.tile(self.start, (sx.size, 1))
        self.bounds = np.zeros(sx.size)

    def iterate(self, active: np.ndarray, iterations: int) -> None:
        """Power iterations on the shifts ``active`` (indices); their bounds only grow."""
        n, lines = self.n, np.arange(self.n)[None, :]
        sx, sy = self.sx[active][:, None], self.sy[active][:, None]
        plus_x, minus_x, plus_y, minus_y = (lines + sx) % n, (lines - sx) % n, (lines + sy) % n, (lines - sy) % n
        rows = np.arange(active.size)[:, None]
        v = self.vectors[active]
        bound = self.bounds[active]
        for _ in range(iterations):
            u = _blocked_product(v[rows, plus_x], self.a_t)[rows, minus_y] - _blocked_product(v, self.b_t)
            bound = np.maximum(bound, np.linalg.norm(u, axis=1))  # ‖v‖ = 1
            v = _blocked_product(u[rows, plus_y], self.a)[rows, minus_x] - _blocked_product(u, self.b)
            length = np.linalg.norm(v, axis=1)
            null = length == 0  # D_sᵀD_s v = 0: restart there (the bound stays valid)
            v[null] = self.start
            v[~null] /= length[~null, None]
        self.vectors[active] = v
        self.bounds[active] = bound


def decode_paper(prev_field, field, search: int = 9) -> tuple[float, float]:
    """The authors' shift search: for dx (outer) and dy (inner) from −search to search, the
    spectral norm ‖roll(prev, (dy, dx)) − field‖₂ (MATLAB ``norm``); the first strict minimum
    wins.

    Exact, with few SVDs: a shift whose lower bound (power iteration, _ShiftNorms) exceeds
    the exact norm of some shift can be neither the minimum nor tied with it. So: bounds for
    all shifts, the exact norm of the lowest bound as a ceiling, more iterations for the
    shifts still under the ceiling, and exact norms, in loop order, for those left."""
    prev_field, field = _check(prev_field, field, search)
    prev_field = prev_field.astype(np.float64)
    field = field.astype(np.float64)
    offsets = np.arange(-search, search + 1)
    sx, sy = (g.ravel() for g in np.meshgrid(offsets, offsets, indexing="ij"))  # dx outer, dy inner
    norms = _ShiftNorms(prev_field, field, sx, sy)
    exact: dict[int, float] = {}

    def norm_of(index: int) -> float:
        if index not in exact:
            exact[index] = _spectral_norm(np.roll(prev_field, (sy[index], sx[index]), axis=(0, 1)) - field)
        return exact[index]

    # Rounding in the bounds (matrix products: ~n ulps of the fields' norms) must not drop
    # the true minimum: a relative and an absolute margin.
    slack = 1e-12 * (np.sqrt(np.einsum("ij,ij->", prev_field, prev_field)) + np.sqrt(np.einsum("ij,ij->", field, field)))

    def beaten(index: int, ceiling: float) -> bool:
        return norms.bounds[index] > ceiling * (1 + 1e-9) + slack

    norms.iterate(np.arange(sx.size), _PAPER_ITERATIONS)
    ceiling = norm_of(int(np.argmin(norms.bounds)))
    running = np.array([i for i in range(sx.size) if i not in exact and not beaten(i, ceiling)], dtype=int)
    if running.size:
        norms.iterate(running, _PAPER_REFINE_ITERATIONS)
    best_index, best = -1, np.inf
    for index in sorted(set(running.tolist()) | exact.keys()):  # ascending = the loop order
        if beaten(index, min(best, ceiling)):
            continue  # its norm exceeds a known one: neither the minimum nor tied with it
        value = norm_of(index)
        if value < best:
            best_index, best = index, value
    return float(sx[best_index]), float(sy[best_index])


def decode_paper_bruteforce(prev_field, field, search: int = 9) -> tuple[float, float]:
    """The authors' loop as written, one LAPACK SVD per shift ((2·search+1)² of them): the
    reference decode_paper is tested against."""
    prev_field, field = _check(prev_field, field, search)
    best, shift = np.inf, (0.0, 0.0)
    for dx in range(-search, search + 1):
        for dy in range(-search, search + 1):
            value = np.linalg.norm(np.roll(prev_field.astype(np.float64), (dy, dx), axis=(0, 1)) - field, 2)
            if value < best:
                best, shift = value, (float(dx), float(dy))
    return shift


DECODERS = {"paper": decode_paper, "fft": decode_fft, "subpixel": decode_subpixel}
