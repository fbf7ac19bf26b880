"""`gridslam bench gridcells`: milliseconds per camera frame of the grid-cell integrator.

For each network size n: the network alone (50 steps, float32 and float64), the authors'
full-sheet formulation of the same steps (4 forward and 1 inverse n×n FFTs per step, float64)
for comparison, the whole frame of GridCellIntegrator.step_world per decoder (network +
decoding + eq. 5), the authors' brute-force `paper` search (one SVD per shift) alone, and the
settling (once per process). Medians over repeated frames of a constant walk that moves the
lattice ~3 neurons per frame; then how each cost grows when n doubles.

The machine is shared: the load average is printed before and after; numbers are only
meaningful when it is low (OpenBLAS and FFT timings degrade badly when the cores are busy).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time

import numpy as np
import scipy.fft

from services.gridcells.decoders import DECODERS, decode_paper_bruteforce
from services.gridcells.integrator import GridCellIntegrator, auto_velocity_scale
from services.gridcells.network import OFFSETS, PREFERRED, GridNetwork, NetworkParams, settled_state, shifted_kernels

SPEED = 0.5  # metres per frame, at 30° from world x; the auto scale maps it to 3 neurons per frame
HEADING = math.radians(30)


def median_ms(call, repeats: int) -> tuple[float, float]:
    """Medians of wall-clock and of this thread's CPU time, ms. On a busy machine the CPU
    time stays close to what the wall clock shows on an idle one (the timed code is
    single-threaded, except the LAPACK SVDs of the brute-force search)."""
    wall, cpu = [], []
    for _ in range(repeats):
        started, started_cpu = time.perf_counter(), time.thread_time()
        call()
        wall.append(time.perf_counter() - started)
        cpu.append(time.thread_time() - started_cpu)
    return 1000 * statistics.median(wall), 1000 * statistics.median(cpu)


class FullSheetNetwork:
    """The authors' frame loop on the full sheet: per step, one n×n FFT per direction
    population, the products with the 4 kernel spectra summed, one inverse FFT (float64).
    The reference the sub-lattice GridNetwork is tested against."""

    def __init__(self, params: NetworkParams, state: np.ndarray | None = None):
        self.params = params
        self.spectra = scipy.fft.rfft2(np.fft.ifftshift(shifted_kernels(params), axes=(-2, -1)))
        self.masks = np.zeros((4, params.n, params.n))
        for d, (i, j) in enumerate(OFFSETS):
            self.masks[d, i::2, j::2] = 1.0
        self.r = np.array(settled_state(params)[0] if state is None else state, dtype=np.float64)

    def run(self, velocity) -> np.ndarray:
        p = self.params
        drive = ((1 + p.alpha * PREFERRED @ np.asarray(velocity))[:, None, None] * self.masks).sum(axis=0)
        for _ in range(p.steps_per_frame):
            recurrent = scipy.fft.irfft2((scipy.fft.rfft2(self.r * self.masks) * self.spectra).sum(axis=0), s=(p.n, p.n))
            field = np.maximum(recurrent + drive, 0.0)
            self.r = np.minimum(p.clip, self.r + p.dt / p.tau * (p.gain * field - self.r))
        return field


def measure(n: int, repeats: int, slow_repeats: int) -> dict[str, float]:
    params = NetworkParams(n=n)
    started = time.perf_counter()
    settled_state(params)  # cold: computed once per process
    row = {"settle_s": time.perf_counter() - started}
    scale = auto_velocity_scale([SPEED], params)
    velocity = (SPEED * scale * math.cos(HEADING), SPEED * scale * math.sin(HEADING))
    for dtype, key in ((np.float32, "network32"), (np.float64, "network64")):
        network = GridNetwork(params, dtype=dtype)
        network.run(velocity)
        row[key] = median_ms(lambda: network.run(velocity), repeats)
    full = FullSheetNetwork(params)
    row["full_sheet"] = median_ms(lambda: full.run(velocity), max(3, repeats // 4))
    for name in DECODERS:
        integrator = GridCellIntegrator(params, decoder=name, velocity_scale=scale, heading0=HEADING)
        for _ in range(3):  # the first frame only stores the pattern; warm the caches
            integrator.step(SPEED, 0.0, 0.0)
        row[name] = median_ms(lambda: integrator.step(SPEED, 0.0, 0.0), slow_repeats if name == "paper" else repeats)
    network = GridNetwork(params, dtype=np.float64)
    previous = network.run(velocity)
    field = network.run(velocity)
    row["brute_force"] = median_ms(lambda: decode_paper_bruteforce(previous, field), slow_repeats)
    return row


ROWS = (
    ("network32", "network, 50 steps, float32"),
    ("network64", "network, 50 steps, float64"),
    ("full_sheet", "network, 50 steps, authors' full-sheet formulation (float64)"),
    ("fft", "whole frame, `fft` decoder"),
    ("subpixel", "whole frame, `subpixel` decoder"),
    ("paper", "whole frame, `paper` decoder"),
    ("brute_force", "`paper` search as the authors wrote it (361 SVDs), alone"),
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="gridslam bench gridcells", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="64,128,256", help="comma-separated network sizes n")
    parser.add_argument("--repeats", type=int, default=40, help="frames timed per configuration")
    parser.add_argument("--slow-repeats", type=int, default=8, help="frames timed for the paper decoders")
    args = parser.parse_args(argv)
    sizes = [int(size) for size in args.sizes.split(",")]
    load_before = " ".join(f"{x:.2f}" for x in os.getloadavg())
    rows = {n: measure(n, args.repeats, args.slow_repeats) for n in sizes}
    print(f"Grid-cell integrator: ms per camera frame, wall clock / thread CPU time, medians of {args.repeats} "
          f"frames ({args.slow_repeats} for the paper decoders); load average before {load_before}, after "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    growth = [f"{a}→{b}" for a, b in zip(sizes, sizes[1:])]
    print("| ms per frame | " + " | ".join(f"n={n}" for n in sizes) + "".join(f" | growth {g} (CPU)" for g in growth) + " |")
    print("|---|" + "---:|" * (len(sizes) + len(growth)))
    for key, title in ROWS:
        cells = [f"{rows[n][key][0]:.2f} / {rows[n][key][1]:.2f}" for n in sizes]
        cells += [f"{rows[b][key][1] / rows[a][key][1]:.1f}×" for a, b in zip(sizes, sizes[1:])]
        print(f"| {title} | " + " | ".join(cells) + " |")
    cells = [f"{rows[n]['settle_s']:.2f} s" for n in sizes] + [f"{rows[b]['settle_s'] / rows[a]['settle_s']:.1f}×" for a, b in zip(sizes, sizes[1:])]
    print("| settling, once per process (wall) | " + " | ".join(cells) + " |")
    return 0
