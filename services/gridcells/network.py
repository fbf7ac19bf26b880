"""The periodic continuous attractor network of grid cells (Burak & Fiete 2009), as Lu et al.
(ROBIO 2016) use it and as their published MATLAB code runs it.

The sheet is n×n neurons on a torus. Every neuron belongs to one of four direction
sub-populations laid out in 2×2 blocks; with 0-based (row, column) parity

    (0, 0) left   (0, 1) up
    (1, 0) down   (1, 1) right

(the authors' ``typeL``, ``typeU``, ``typeD``, ``typeR``). A neuron of direction d projects
through the centre-surround kernel W0(x) = a·exp(−γ|x|²) − exp(−β|x|²) (Burak & Fiete eq. 3,
β = 3/λ², γ = 1.05β) shifted by l neurons: +l columns for right, −l for left, +l rows for down,
−l rows for up. Its feed-forward input is B = 1 + α·(e_d·v) (eq. 4) with e_right = (1, 0),
e_left = (−1, 0), e_up = (0, 1), e_down = (0, −1) in world (x, y). So the activity lattice
flows toward larger columns when the agent moves toward world +x and toward smaller rows
when it moves toward world +y.

One network step, as the authors' code does it (their code differs from the paper's text in
the gain 5 and the clip at 10):

    f = max(0, W*r + B)                            rectified field (what decoders compare)
    r ← min(clip, r + dt/τ·(gain·f − r))           gain 5, clip 10

Speed: the 2×2 layout makes the sheet four interleaved (n/2)×(n/2) sub-lattices, one per
direction. The recurrent input of sub-lattice e is Σ_d k_ed ⊛ r_d, a periodic convolution on
the sub-lattice with k_ed(M) = W_d(2M + o_e − o_d), so one step is 4 forward and 4 inverse
real FFTs of (n/2)² with 16 precomputed kernel spectra (DESIGN.md), and the state is kept in
that (4, n/2, n/2) layout between steps.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from dataclasses import dataclass, fields

import numpy as np
import scipy.fft

from services.common.environment import process_setting
from services.common.errors import ConfigError, DataError

log = logging.getLogger(__name__)

# γ/β of Burak & Fiete eq. 3 (the authors' ``alphabar``).
GAMMA_OVER_BETA = 1.05

# Direction sub-populations in sub-lattice order: name, (row parity, column parity), and the
# world unit vector e_d of eq. 4. The order is the 2×2 block read row by row.
DIRECTIONS = ("left", "up", "down", "right")
OFFSETS = ((0, 0), (0, 1), (1, 0), (1, 1))
PREFERRED = np.array([(-1.0, 0.0), (0.0, 1.0), (0.0, -1.0), (1.0, 0.0)])


class GridCellError(DataError):
    """Input the grid-cell integrator cannot use (NaN/inf motion, bad array shapes)."""


@dataclass(frozen=True)
class NetworkParams:
    """Network parameters. Defaults are the paper's and the authors' code's values."""

    n: int = 128  # neurons per side of the torus (even: 2×2 direction blocks)
    l: int = 2  # kernel shift along the preferred direction, neurons (B&F eq. 2, ``wtphase``)
    tau: float = 5.0  # neuron time constant, ms
    dt: float = 0.5  # integration step, ms
    lam: float = 18.0  # λ of eq. 3 (β = 3/λ²); the lattice that forms has a period of ~27
    a: float = 1.0  # excitatory amplitude of eq. 3 (a ≤ (γ/β)²)
    alpha: float = 2.0  # velocity gain of eq. 4 (0.2 suggested for very fast vehicles)
    steps_per_frame: int = 50  # network steps per camera frame
    settle_steps: int = 1000  # zero-velocity steps from r = 0 before the first frame
    envelope_steps: int = 800  # settling steps 1..envelope_steps-1 use the envelope input
    gain: float = 5.0  # authors' code: r ← r + dt/τ·(gain·f − r)
    clip: float = 10.0  # authors' code: r ≤ clip

    def __post_init__(self) -> None:
        if self.n < 8 or self.n % 2:
            raise ConfigError(f"network size n={self.n}: must be an even number >= 8 (2×2 direction blocks)")
        if not 0 <= self.l < self.n // 2:
            raise ConfigError(f"kernel shift l={self.l}: must be in [0, n/2)")
        for name in ("tau", "dt", "lam", "gain", "clip"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"network parameter {name}={value}: must be a positive number")
        for name in ("a", "alpha"):
            if not np.isfinite(getattr(self, name)):
                raise ConfigError(f"network parameter {name}={getattr(self, name)}: must be finite")
        if self.steps_per_frame < 1 or self.settle_steps < 0 or self.envelope_steps < 0:
            raise ConfigError("steps_per_frame must be >= 1, settle_steps and envelope_steps >= 0")


def shifted_kernels(params: NetworkParams) -> np.ndarray:
    """The four shifted weight kernels, shape (4, n, n), in the authors' array layout: the
    kernel centre x = 0 sits at index n/2 (x runs from −n/2 to n/2−1), float64."""
    n = params.n
    beta = 3.0 / params.lam**2
    xbar2 = beta * np.arange(-n // 2, n // 2, dtype=np.float64) ** 2
    dist2 = xbar2[:, None] + xbar2[None, :]
    filt = params.a * np.exp(-GAMMA_OVER_BETA * dist2) - np.exp(-dist2)
    # Circular shift within the n×n kernel array, as the authors' circshift does.
    shifts = {"left": (0, -params.l), "up": (-params.l, 0), "down": (params.l, 0), "right": (0, params.l)}
    return np.stack([np.roll(filt, shifts[d], axis=(0, 1)) for d in DIRECTIONS])


def split(full: np.ndarray) -> np.ndarray:
    """(…, n, n) sheet → (…, 4, n/2, n/2) direction sub-lattices (order of DIRECTIONS)."""
    return np.stack([full[..., i::2, j::2] for i, j in OFFSETS], axis=-3)


def merge(sub: np.ndarray) -> np.ndarray:
    """(…, 4, m, m) sub-lattices → (…, 2m, 2m) sheet; the inverse of split()."""
    m = sub.shape[-1]
    full = np.empty(sub.shape[:-3] + (2 * m, 2 * m), dtype=sub.dtype)
    for d, (i, j) in enumerate(OFFSETS):
        full[..., i::2, j::2] = sub[..., d, :, :]
    return full


def _settle_key(params: NetworkParams) -> NetworkParams:
    # Settling does not depend on the velocity gain or the steps per frame: normalise them so
    # networks that differ only there share one cached settled state.
    return NetworkParams(**{f.name: getattr(params, f.name) for f in fields(params)} | {"alpha": 2.0, "steps_per_frame": 50})


def settled_state(params: NetworkParams = NetworkParams()) -> tuple[np.ndarray, np.ndarray]:
    """The state r and rectified field f after the authors' settling, float64, read-only.

    Deterministic and the same for every run with these parameters, so it is computed once
    per process (a cached pure function; callers get read-only arrays and copy them).

    Fidelity: with the defaults it matches the state the authors' code reaches in GNU Octave
    (``seed_reference/settled_state_128x128.csv``, printed to 10 significant digits) within
    5.1e-10 absolute, i.e. 1.8e-10 of the largest rate: the CSV's own rounding.

    Note what that state is: because all settling steps use the aperiodic convolution, the
    lattice it holds is not periodic on the torus (its strongest wavevectors, in (row,
    column) cycles per sheet, are (5, 0) and (3, 4), with (0, 4) and (4, 0) close behind).
    Under the periodic frame dynamics it re-forms into a hexagonal torus lattice ((3, 4),
    (5, −1), (2, −5): periods 25.6, 25.1 and 23.8 neurons, 57–64° apart) over about 30
    frames. At zero velocity that re-forming moves the lattice by 0.07 neurons in the first
    frame and by less than 0.02 neurons per frame after (measured with decode_subpixel), so it
    does not disturb the decoded flow.
    """
    return _settled_state(_settle_key(params))


@functools.lru_cache(maxsize=4)
def _settled_state(params: NetworkParams) -> tuple[np.ndarray, np.ndarray]:
    """The authors' settling, as their code runs it before the first frame:

    r = 0; for iter = 1..settle_steps: B = 1 (zero velocity) times the envelope
    exp(−4|x|²/(n/2)²) while iter < envelope_steps and 1 from then on; the recurrent input is
    the zero-padded (aperiodic) convolution for *all* settling steps (their ``ftX`` spectra of
    a 2n×2n FFT; only the frames use the periodic ``ftX_small``); f = max(0, W*r + B);
    r ← min(clip, r + dt/τ·(gain·f − r)).

    Computed on the four sub-lattices like the periodic step: the aperiodic kernel from
    sub-lattice d to e, k_ed(M) = W_d(2M + o_e − o_d) for 2M + o_e − o_d within the kernel
    array [−n/2, n/2), is needed for |M| < n/2 only, so n×n FFTs of the zero-padded
    (n/2)×(n/2) sub-lattices give the linear convolution without wrap-around: 4 forward and
    4 inverse n×n FFTs per step instead of 4 forward and 1 inverse 2n×2n.
    """
    n, m, half = params.n, params.n // 2, params.n // 2
    kernels = shifted_kernels(params)  # centre x = 0 at index n/2; zero outside [−n/2, n/2)
    lag = np.arange(n)
    lag = np.where(lag < m, lag, lag - n)  # M for each index of the n×n padded grid
    sub_kernels = np.zeros((4, 4, n, n))
    for e, (ei, ej) in enumerate(OFFSETS):
        for d, (di, dj) in enumerate(OFFSETS):
            rows, cols = 2 * lag + ei - di + half, 2 * lag + ej - dj + half  # kernel array indices
            inside_r, inside_c = (rows >= 0) & (rows < n), (cols >= 0) & (cols < n)
            block = kernels[d][np.ix_(np.clip(rows, 0, n - 1), np.clip(cols, 0, n - 1))]
            sub_kernels[e, d] = block * inside_r[:, None] * inside_c[None, :]
    kernel_spectra = scipy.fft.rfft2(sub_kernels)
    x = np.arange(-half, half, dtype=np.float64)
    envelope = split(np.exp(-4.0 * (x[:, None] ** 2 + x[None, :] ** 2) / half**2))
    rate = params.dt / params.tau
    r = np.zeros((4, m, m))
    field = np.zeros((4, m, m))
    for iteration in range(1, params.settle_steps + 1):
        feedforward = envelope if iteration < params.envelope_steps else 1.0
        rates = scipy.fft.rfft2(r, s=(n, n))
        spectrum = (kernel_spectra * rates[None]).sum(axis=1)
        recurrent = scipy.fft.irfft2(spectrum, s=(n, n))[:, :m, :m]
        field = np.maximum(recurrent + feedforward, 0.0)
        r = np.minimum(params.clip, r + rate * (params.gain * field - r))
    r, field = merge(r), merge(field)
    r.setflags(write=False)
    field.setflags(write=False)
    log.debug("settled a %d×%d network in %d steps", n, n, params.settle_steps)
    return r, field


def velocity_input(params: NetworkParams, velocity: tuple[float, float]) -> np.ndarray:
    """B = 1 + α·(e_d·v) per direction sub-population (B&F eq. 4), shape (4,)."""
    vx, vy = velocity
    if not (np.isfinite(vx) and np.isfinite(vy)):
        raise GridCellError(f"network velocity ({vx}, {vy}) is not finite")
    return 1.0 + params.alpha * (PREFERRED @ np.array([vx, vy], dtype=np.float64))


class GridNetwork:
    """The n×n periodic network. ``run(v)`` advances one camera frame (steps_per_frame steps)
    with the world-frame velocity v in network units per frame and returns the rectified
    field of the last step."""

    def __init__(self, params: NetworkParams = NetworkParams(), *, dtype=np.float32, settle: bool = True):
        self.params = params
        self.dtype = np.dtype(dtype)
        if self.dtype not in (np.float32, np.float64):
            raise ConfigError(f"network dtype {self.dtype}: must be float32 or float64")
        m = params.n // 2
        periodic = np.fft.ifftshift(shifted_kernels(params), axes=(-2, -1))  # centre x = 0 at index 0
        # k_ed(M) = W_d(2M + o_e − o_d): rows e (output sub-lattice), columns d (input).
        sub_kernels = np.empty((4, 4, m, m))
        for e, (ei, ej) in enumerate(OFFSETS):
            for d, (di, dj) in enumerate(OFFSETS):
                sub_kernels[e, d] = np.roll(periodic[d], (di - ei, dj - ej), axis=(0, 1))[::2, ::2]
        complex_dtype = np.result_type(self.dtype, np.complex64)
        self._kernel_spectra = scipy.fft.rfft2(sub_kernels).astype(complex_dtype)
        self._decay = self.dtype.type(1.0 - params.dt / params.tau)
        self._drive = self.dtype.type(params.dt / params.tau * params.gain)
        self._clip = self.dtype.type(params.clip)
        self._r = np.zeros((4, m, m), dtype=self.dtype)
        self._f = np.zeros((4, m, m), dtype=self.dtype)
        if settle:
            self.settle()

    # --- state -----------------------------------------------------------------------------
    @property
    def state(self) -> np.ndarray:
        """r, the n×n activity (a copy)."""
        return merge(self._r)

    @state.setter
    def state(self, value: np.ndarray) -> None:
        value = np.asarray(value)
        n = self.params.n
        if value.shape != (n, n):
            raise GridCellError(f"network state has shape {value.shape}, expected ({n}, {n})")
        if not np.all(np.isfinite(value)):
            raise GridCellError("network state contains NaN or inf")
        self._r = split(value).astype(self.dtype)

    @property
    def field(self) -> np.ndarray:
        """f, the rectified field of the last step, n×n (a copy; what decoders compare)."""
        return merge(self._f)

    def settle(self) -> None:
        """Reset to the authors' settled state (1000 steps from r = 0; cached per process)."""
        r, f = settled_state(self.params)
        self._r = split(r).astype(self.dtype)
        self._f = split(f).astype(self.dtype)

    # --- dynamics --------------------------------------------------------------------------
    def run(self, velocity: tuple[float, float], steps: int | None = None) -> np.ndarray:
        """Advance one frame (``steps_per_frame`` steps, or ``steps``) with B = 1 + α·(e_d·v),
        v the world-frame velocity in network units per frame. Returns the field (a copy)."""
        feedforward = velocity_input(self.params, velocity).astype(self.dtype)[:, None, None]
        m = self.params.n // 2
        r, f, kernels = self._r, self._f, self._kernel_spectra
        for _ in range(self.params.steps_per_frame if steps is None else steps):
            # Recurrent input of sub-lattice e: Σ_d k_ed ⊛ r_d, in the Fourier domain.
            spectrum = (kernels * scipy.fft.rfft2(r)[None]).sum(axis=1)
            recurrent = scipy.fft.irfft2(spectrum, s=(m, m), overwrite_x=True)
            np.add(recurrent, feedforward, out=f)
            np.maximum(f, 0, out=f)
            # r ← min(clip, (1 − dt/τ)·r + dt/τ·gain·f)
            r *= self._decay
            r += self._drive * f
            np.minimum(r, self._clip, out=r)
        return self.field


# --- the fast, batched float32 network ----------------------------------------------------------
# The recurrent kernel is a difference of Gaussians: its spectrum falls below 1e-9 of its peak
# beyond ~0.15 cycles per neuron at λ = 18. On those bins the 4×4 sub-lattice kernel matrix is
# of rank one, K_ed(k) = P_e(k)·A_d(k) (the aliases of a sub-lattice frequency carry nothing), so
# the product is 4 multiply-adds and 4 multiplies per bin of the band instead of 16, and the
# bins outside the band stay zero. BAND_EPSILON bounds what is dropped, relative to the peak.
BAND_EPSILON = 1e-9
FFT_BACKENDS = ("fftw", "scipy")


def fft_backend() -> str:
    """The FFT library the fast network uses: pyFFTW (FFTW 3, about twice scipy.fft's speed on
    the 64×64 sub-lattices) when it is installed (`pip install gridslam[fftw]`), scipy.fft
    otherwise; the process's `fft` setting (GRIDSLAM_FFT=fftw|scipy, services/common/environment.py)
    forces one."""
    choice = process_setting("fft")
    if choice == "scipy":
        return "scipy"
    try:
        import pyfftw  # noqa: F401
    except ImportError:
        if choice == "fftw":
            raise ConfigError("GRIDSLAM_FFT=fftw but pyFFTW is not installed (pip install 'gridslam[fftw]')") from None
        return "scipy"
    return "fftw"


def _rank_one_factors(params: NetworkParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(P, A, band): P (4, m, m/2+1) and A (4, m, m/2+1) with K_ed(k) = P_e(k)·A_d(k) on the
    bins of ``band`` (m, m/2+1, bool), the bins where the kernel's spectrum is above
    BAND_EPSILON of its peak; float64/complex128.

    K_ed(k) = ¼ Σ over the four aliases q ≡ k (mod m) of Ŵ_d(q)·e^{2πi q·(o_e − o_d)/n}; keeping
    the alias of smallest |q| (the others are below BAND_EPSILON there) factorises it."""
    n, m = params.n, params.n // 2
    qy = np.fft.fftfreq(m, 1.0 / m)[:, None]  # sub-lattice frequency, represented in [-m/2, m/2)
    qx = np.fft.rfftfreq(m, 1.0 / m)[None, :]
    base = np.fft.ifftshift(shifted_kernels(dataclasses.replace(params, l=0))[0])  # W0 centred at index 0
    spectrum = scipy.fft.fft2(base)[qy.astype(int) % n, qx.astype(int) % n].real  # W0 is even
    band = np.abs(spectrum) > BAND_EPSILON * np.abs(spectrum).max()
    shifts = {"left": (0, -params.l), "up": (-params.l, 0), "down": (params.l, 0), "right": (0, params.l)}
    phase = lambda rows, cols: np.exp(2j * np.pi * (qy * rows + qx * cols) / n)  # noqa: E731
    p = np.stack([phase(i, j) * np.ones_like(spectrum) for i, j in OFFSETS])
    a = np.stack([0.25 * spectrum * phase(-(i + shifts[d][0]), -(j + shifts[d][1])) for d, (i, j) in zip(DIRECTIONS, OFFSETS)])
    return p, a, band


class NetworkStack:
    """Several periodic networks of the same size n (grid modules: they may differ in λ, α and
    the other parameters, not in n or steps_per_frame) run together in float32, one batched
    FFT per step for all of them. Same dynamics as GridNetwork (tests hold it to float32
    precision of the float64 reference); faster:

    - the velocity input B is added to the zero-frequency bin of the recurrent spectrum, and the
      gain dt/τ·gain is folded into the kernel (the state is kept as r / (dt/τ·gain)), so a step
      is a forward FFT, the kernel product, an inverse FFT and four in-place array operations;
    - the kernel product runs on the band where the kernel is not negligible, in its rank-one
      form (see _rank_one_factors), when that form matches the exact kernel to 1e-6 of its peak
      (λ = 18 at n = 128: 5e-8); otherwise (λ = 18 on a 64² sheet, which truncates the kernel)
      on all bins with the full 4×4 product;
    - FFTW (pyFFTW) plans on fixed buffers when it is installed, scipy.fft otherwise
      (fft_backend()); both pruned to the band's columns with the rank-one product (the forward
      transform's second pass and the inverse's first run on those columns only).
    """

    def __init__(self, params: NetworkParams | tuple[NetworkParams, ...] = NetworkParams(), *, settle: bool = True,
                 backend: str | None = None):
        self.modules = (params,) if isinstance(params, NetworkParams) else tuple(params)
        if not self.modules:
            raise ConfigError("a network stack needs at least one module")
        first = self.modules[0]
        if any(p.n != first.n or p.steps_per_frame != first.steps_per_frame for p in self.modules):
            raise ConfigError("the modules of a stack must share n and steps_per_frame")
        self.params = first
        self.backend = backend or fft_backend()
        b, m = len(self.modules), first.n // 2
        shape, spectral = (b, 4, m, m), (b, 4, m, m // 2 + 1)
        self._drive = np.array([p.dt / p.tau * p.gain for p in self.modules])
        # Full arrays, not broadcast scalars: numpy's maximum and minimum take a vectorised
        # path only for operands of equal shape (3-4× faster here).
        self._decay = np.array([1.0 - p.dt / p.tau for p in self.modules], dtype=np.float32)[:, None, None, None]
        self._ceiling = np.broadcast_to(np.array([p.clip / d for p, d in zip(self.modules, self._drive)], dtype=np.float32)[:, None, None, None], shape).copy()
        self._zeros = np.zeros(shape, dtype=np.float32)
        self._alpha = np.array([p.alpha for p in self.modules])
        # Unnormalised forward and inverse transforms: 1/m² goes into the kernel.
        scale = self._drive[:, None, None, None] / m**2
        factors = [_rank_one_factors(p) for p in self.modules]
        exact = np.stack([_sub_kernel_spectra(p) for p in self.modules])  # (B, 4, 4, m, m/2+1)
        rows = np.flatnonzero(np.any(np.stack([band for _, _, band in factors]), axis=(0, 2)))
        cols = np.flatnonzero(np.any(np.stack([band for _, _, band in factors]), axis=(0, 1)))
        approx = np.stack([p[:, None] * a[None] for p, a, _ in factors])
        inside = np.zeros(exact.shape[-2:], dtype=bool)
        inside[np.ix_(rows, cols)] = True
        error = np.max(np.abs(np.where(inside, approx, 0) - exact)) / np.max(np.abs(exact))
        self.rank_one = bool(error < 1e-6)
        if self.rank_one:
            # The band as two blocks of `rows` rows, [0, rows) and [m − rows, m), of the first
            # `width` columns: one strided view (band_view) of every spectral array.
            self._band_rows = max(int(rows[rows < m // 2].max()) + 1, m - int(rows[rows >= m // 2].min()) if np.any(rows >= m // 2) else 0)
            self._width = int(cols.max()) + 1
            p_all = np.stack([p for p, _, _ in factors]).astype(np.complex64)
            a_all = (np.stack([a for _, a, _ in factors]) * scale).astype(np.complex64)
            self._p = self._band_view(p_all).copy()
            self._a = self._band_view(a_all).copy()
            self._total = np.empty((b,) + self._p.shape[2:], dtype=np.complex64)
            self._terms = np.empty(self._a.shape, dtype=np.complex64)
        else:
            self._kernels = (exact * scale[:, :, None]).astype(np.complex64)
        log.debug("network stack: %d module(s), n=%d, %s FFT, %s kernel product (rank-one error %.1e)", b, first.n, self.backend,
                  "band rank-one" if self.rank_one else "full 4×4", error)
        if self.backend == "fftw":
            import pyfftw

            self._r = pyfftw.empty_aligned(shape, dtype=np.float32)
            self._rates = pyfftw.empty_aligned(spectral, dtype=np.complex64)
            self._spectrum = pyfftw.empty_aligned(spectral, dtype=np.complex64)
            self._h = pyfftw.empty_aligned(shape, dtype=np.float32)
            plan = functools.partial(pyfftw.FFTW, flags=("FFTW_MEASURE",), threads=1)
            if self.rank_one:
                # Pruned: the product needs, and the recurrent spectrum has, only the first
                # `width` columns. Forward: rows (real to complex), then those columns.
                # Inverse: those columns into a buffer whose other columns are zero, then rows
                # (complex to real, which overwrites its input: the zero columns are cleared
                # again each step). The spectrum itself is never overwritten outside the band.
                w = self._width
                self._columns = pyfftw.empty_aligned(spectral, dtype=np.complex64)
                self._columns[...] = 0
                steps = [plan(self._r, self._rates, axes=(-1,)), plan(self._rates[..., :w], self._rates[..., :w], axes=(-2,))]
                self._forward = lambda: [step.execute() for step in steps]
                inverse = [plan(self._spectrum[..., :w], self._columns[..., :w], axes=(-2,), direction="FFTW_BACKWARD"),
                           plan(self._columns, self._h, axes=(-1,), direction="FFTW_BACKWARD")]
                tail = self._columns[..., w:]
                self._inverse = lambda: (inverse[0].execute(), tail.fill(0), inverse[1].execute())
            else:  # (the full product rewrites the whole spectrum, which the inverse overwrites)
                self._forward = plan(self._r, self._rates, axes=(-2, -1)).execute
                self._inverse = plan(self._spectrum, self._h, axes=(-2, -1), direction="FFTW_BACKWARD").execute
        else:
            self._r = np.zeros(shape, dtype=np.float32)
            self._rates = np.zeros(spectral, dtype=np.complex64)
            self._spectrum = np.zeros(spectral, dtype=np.complex64)
            self._h = np.zeros(shape, dtype=np.float32)
            self._columns = np.zeros(spectral, dtype=np.complex64)   # the band's columns; the others stay zero
        self._r[...] = 0
        self._spectrum[...] = 0
        if self.rank_one:
            self._rates_band, self._spectrum_band = self._band_view(self._rates), self._band_view(self._spectrum)
        self._f = np.zeros(shape, dtype=np.float32)
        if settle:
            self.settle()

    # --- state ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.modules)

    @property
    def state(self) -> np.ndarray:
        """r of every module, (B, n, n) float64 (a copy)."""
        return merge(self._r.astype(np.float64) * self._drive[:, None, None, None])

    @state.setter
    def state(self, value: np.ndarray) -> None:
        value = np.asarray(value, dtype=np.float64)
        n = self.params.n
        if value.shape != (len(self), n, n):
            raise GridCellError(f"network state has shape {value.shape}, expected ({len(self)}, {n}, {n})")
        if not np.all(np.isfinite(value)):
            raise GridCellError("network state contains NaN or inf")
        self._r[...] = split(value) / self._drive[:, None, None, None]

    @property
    def fields(self) -> np.ndarray:
        """f of every module after the last step, (B, n, n) float32 (a copy)."""
        return merge(self._f)

    def set_field(self, value: np.ndarray) -> None:
        self._f[...] = split(np.asarray(value, dtype=np.float32))

    def settle(self) -> None:
        """Every module to the authors' settled state (settled_state, cached per process)."""
        settled = [settled_state(p) for p in self.modules]
        self.state = np.stack([r for r, _ in settled])
        self.set_field(np.stack([f for _, f in settled]))

    # --- dynamics ------------------------------------------------------------------------------
    def run(self, velocity, steps: int | None = None) -> np.ndarray:
        """Advance every module one frame with the world velocity v (network units per frame;
        a (B, 2) array gives each module its own); returns the fields (B, n, n) float32."""
        velocity = np.asarray(velocity, dtype=np.float64)
        if velocity.shape not in ((2,), (len(self), 2)):
            raise GridCellError(f"network velocity of shape {velocity.shape}: expected (2,) or ({len(self)}, 2)")
        if not np.all(np.isfinite(velocity)):
            raise GridCellError(f"network velocity {velocity.tolist()} is not finite")
        m = self.params.n // 2
        feedforward = 1.0 + self._alpha[:, None] * (np.atleast_2d(velocity) @ PREFERRED.T)
        dc = feedforward.astype(np.complex64)  # B on the zero-frequency bin (unnormalised inverse)
        r, f, h, rates, spectrum = self._r, self._f, self._h, self._rates, self._spectrum
        decay, ceiling, zeros = (self._decay if len(self) > 1 else self._decay.item()), self._ceiling, self._zeros
        fftw, w = self.backend == "fftw", (self._width if self.rank_one else m)   # w: the band's columns
        for _ in range(self.params.steps_per_frame if steps is None else steps):
            if fftw:
                self._forward()
            elif self.rank_one:   # pruned to the band's columns, as with FFTW
                rates[..., :w] = scipy.fft.fft(scipy.fft.rfft(r, axis=-1)[..., :w], axis=-2, overwrite_x=True)
            else:
                rates[...] = scipy.fft.rfft2(r)
            self._product()
            spectrum[:, :, 0, 0] += dc
            if fftw:
                self._inverse()
            elif self.rank_one:
                self._columns[..., :w] = scipy.fft.ifft(spectrum[..., :w], axis=-2, norm="forward")
                h[...] = scipy.fft.irfft(self._columns, n=m, axis=-1, norm="forward")
            else:
                h[...] = scipy.fft.irfft2(spectrum, s=(m, m), norm="forward")
            np.maximum(h, zeros, out=f)
            r *= decay
            r += f
            np.minimum(r, ceiling, out=r)
        return self.fields

    def _band_view(self, spectral: np.ndarray) -> np.ndarray:
        """(…, 4, m, m/2+1) → the band as a (…, 4, 2, rows, width) view (writable)."""
        m, rows = spectral.shape[-2], self._band_rows
        row_stride, col_stride = spectral.strides[-2:]
        return np.lib.stride_tricks.as_strided(
            spectral, shape=spectral.shape[:-2] + (2, rows, self._width),
            strides=spectral.strides[:-2] + ((m - rows) * row_stride, row_stride, col_stride))

    def _product(self) -> None:
        """The recurrent spectrum (self._spectrum) from the rates' (self._rates)."""
        if not self.rank_one:
            np.einsum("bedij,bdij->beij", self._kernels, self._rates, out=self._spectrum)
            return
        np.multiply(self._a, self._rates_band, out=self._terms)
        np.sum(self._terms, axis=1, out=self._total)
        np.multiply(self._p, self._total[:, None], out=self._spectrum_band)


def _sub_kernel_spectra(params: NetworkParams) -> np.ndarray:
    """The 16 sub-lattice kernel spectra k_ed, (4, 4, m, m/2+1) complex128 (see GridNetwork)."""
    m = params.n // 2
    periodic = np.fft.ifftshift(shifted_kernels(params), axes=(-2, -1))
    sub_kernels = np.empty((4, 4, m, m))
    for e, (ei, ej) in enumerate(OFFSETS):
        for d, (di, dj) in enumerate(OFFSETS):
            sub_kernels[e, d] = np.roll(periodic[d], (di - ei, dj - ej), axis=(0, 1))[::2, ::2]
    return scipy.fft.rfft2(sub_kernels)
