"""The grid code (issue 13): the position read from the phases of the modules' lattices
rather than integrated from their flow frame by frame.

A module's lattice is a sum of three plane waves (wavevectors k_j, integer cycles per sheet:
the lattice is commensurate with the torus). Moving the lattice by D neurons turns the
Fourier coefficient of the field at k_j by φ_j = −2π k_j·D / n, so the three phases give the
lattice's displacement since its warm start modulo its lattice vectors, whatever happened in
between. A world displacement x (input units) moves module i's lattice by G_i·x (G_i: the
module's mean calibrated gain times the velocity scale, a complex number in the world-complex
convention of calibration.py, turned by the module's orientation), so each module says where the agent is modulo its spacing, and
several modules with different spacings (and lattice orientations) together pin it down
(Fiete, Burak & Brookings 2008). `GridCode.decode` maximises Σ_ij cos(φ_ij − φ_ij(x)) over x
within a radius of a prior (the integrated position): on a grid of candidates, then Newton
steps.

What it cannot do: the lattice flow deviates from G_i·x by the calibrated direction and speed
errors (up to a few tenths of a degree and percent), and those deviations accumulate in the
phases; the integrated position takes them out frame by frame. docs/gridcells.md compares both.
"""

from __future__ import annotations

import math

import numpy as np

from services.gridcells.calibration import FlowTable


def lattice_wavevectors(field: np.ndarray, count: int = 3) -> np.ndarray:
    """The ``count`` strongest wavevectors (ky, kx) of a lattice, integer cycles per sheet, one
    per ± pair, frequencies above 0.2 cycles per neuron (the 2×2 input pattern) left out."""
    n = field.shape[0]
    power = np.abs(np.fft.fft2(field - field.mean())) ** 2
    k = np.rint(np.fft.fftfreq(n) * n).astype(int)
    ky, kx = np.meshgrid(k, k, indexing="ij")
    power[(np.hypot(kx, ky) > 0.2 * n) | (ky < 0) | ((ky == 0) & (kx <= 0))] = 0
    best = np.argsort(power.ravel())[::-1][:count]
    return np.column_stack([ky.flat[best], kx.flat[best]])


class GridCode:
    """Phases of every module's lattice and the position they encode."""

    def __init__(self, tables: tuple[FlowTable, ...], velocity_scale: float, rotations=None):
        self.tables = tables
        n = tables[0].params.n
        self.n = n
        rows = np.arange(n)
        self._waves, self._reference, coefficients, spacings = [], [], [], []
        rotations = np.ones(len(tables)) if rotations is None else np.asarray(rotations)
        for table, rotation in zip(tables, rotations):
            waves = lattice_wavevectors(table.warm_field)
            basis = np.exp(-2j * np.pi * (waves[:, 0, None, None] * rows[None, :, None] + waves[:, 1, None, None] * rows[None, None, :]) / n)
            self._waves.append(basis)
            self._reference.append(np.einsum("kij,ij->k", basis, table.warm_field.astype(np.float64)))
            # The mean gain over the linear range (drives 0.03 to 0.25) and all directions.
            drives = table.speeds * table.params.alpha
            gain = velocity_scale * rotation * table.gain[:, (drives >= 0.03) & (drives <= 0.25)].mean()
            ky, kx = waves[:, 0].astype(float), waves[:, 1].astype(float)
            # φ(x) = −2π/n (kx·Re w − ky·Im w), w = gain·x: linear in (Re x, Im x).
            a = -2 * np.pi / n * (kx * gain.real - ky * gain.imag)
            b = -2 * np.pi / n * (-kx * gain.imag - ky * gain.real)
            coefficients.append(np.column_stack([a, b]))
            spacings.append(2 * np.pi / np.hypot(a, b).max())  # the module's spacing in input units (about)
        self._coefficients = np.vstack(coefficients)  # (modules·3, 2)
        self.spacings = np.array(spacings)

    def phases(self, fields: np.ndarray) -> np.ndarray:
        """φ_ij of the fields (modules, n, n) against the warm fields, (modules·3,) rad."""
        phases = [np.angle(np.einsum("kij,ij->k", basis, np.asarray(field, dtype=np.float64)) / reference)
                  for basis, reference, field in zip(self._waves, self._reference, fields)]
        return np.concatenate(phases)

    def score(self, positions: np.ndarray, phases: np.ndarray) -> np.ndarray:
        """Σ_ij cos(φ_ij − φ_ij(x)) for complex positions (input units, world frame)."""
        predicted = np.outer(positions.real, self._coefficients[:, 0]) + np.outer(positions.imag, self._coefficients[:, 1])
        return np.cos(phases[None, :] - predicted).sum(axis=1)

    def decode(self, fields: np.ndarray, prior: complex, radius: float | None = None) -> complex:
        """The position (complex, input units) whose phases best match the fields', within
        ``radius`` (default: the largest module spacing) of ``prior``."""
        phases = self.phases(fields)
        radius = float(self.spacings.max()) if radius is None else radius
        step = float(self.spacings.min()) / 12
        offsets = np.arange(-radius, radius + step / 2, step)
        grid = prior + offsets[:, None] + 1j * offsets[None, :]
        grid = grid[np.abs(grid - prior) <= radius]
        best = complex(grid[int(np.argmax(self.score(grid, phases)))])
        x = np.array([best.real, best.imag])
        c = self._coefficients
        for _ in range(6):  # Newton on the score: gradient Σ sin(Δ)·c, Hessian −Σ cos(Δ)·c cᵀ
            delta = phases - c @ x
            gradient = c.T @ np.sin(delta)
            hessian = -(c * np.cos(delta)[:, None]).T @ c
            if not np.all(np.linalg.eigvalsh(hessian) < 0):
                break
            step_x = -np.linalg.solve(hessian, gradient)
            x += step_x
            if math.hypot(*step_x) < 1e-12 * max(1.0, abs(best)):
                break
        return complex(x[0], x[1])
