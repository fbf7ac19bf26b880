"""`gridslam bench gridcells`: milliseconds per camera frame of the grid-cell integrator.

For each network size n: the network alone (50 steps): GridNetwork (the sub-lattice form,
float32 and float64), the authors' full-sheet formulation of the same steps (4 forward and 1
inverse n×n FFTs per step, float64), and NetworkStack (the fast float32 form: band-limited
rank-one kernel product, input on the zero-frequency bin, FFTW when installed, else
scipy.fft) with one and three modules; the whole frame of GridCellIntegrator.step per decoder
(network + decoding + eq. 5), today's formulation (`subpixel` on GridNetwork float32) beside
the `calibrated` decoder with one and three modules and the ring heading, as ratios from the
same run; the authors' brute-force `paper` search (one SVD per shift) alone, and the settling
(once per process). Medians over repeated frames of a constant walk that moves the lattice ~3
neurons per frame; then how each cost grows when n doubles.

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

from services.benchmarks.timing import median_ms
from services.common.settings import CommandParser
from services.gridcells.calibration import CalibrationGrid, LagInverter, check_flows, check_velocities, flow_table, lag_components
from services.gridcells.decoders import DECODERS, decode_paper_bruteforce, decode_subpixel
from services.gridcells.heading import HeadDirectionRing, RingHeading, ring_calibration
from services.gridcells.integrator import LATTICE_RATE, GridCellIntegrator, auto_velocity_scale, module_params
from services.gridcells.network import (
    OFFSETS,
    PREFERRED,
    GridNetwork,
    NetworkParams,
    NetworkStack,
    fft_backend,
    settled_state,
    shifted_kernels,
)

# Timing does not depend on how finely the flow is tabulated: a coarse table, not cached.
TIMING_GRID = CalibrationGrid(directions=4, axis_span_deg=0, drives=(0.05, 0.2, 0.3), settle_frames=1, min_frames=2,
                              check_frames=0, warm_frames=5)

SPEED = 0.5  # metres per frame, at 30° from world x; the auto scale maps it to 3 neurons per frame
HEADING = math.radians(30)


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


class TodayFrame:
    """The whole frame as the integrator computed it before issue 13: GridNetwork float32
    (sub-lattice FFTs, 16 kernel products) and decode_subpixel on each pair of fields (eq. 5's
    arithmetic is negligible)."""

    def __init__(self, params: NetworkParams, velocity):
        self.network, self.velocity = GridNetwork(params), velocity
        self.previous = self.network.field

    def step(self, *_increment) -> None:
        field = self.network.run(self.velocity)
        decode_subpixel(self.previous, field)
        self.previous = field


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
    backends = ("fftw", "scipy") if fft_backend() == "fftw" else ("scipy",)
    for backend in backends:
        for count in (1, 3):
            stack = NetworkStack(module_params(params, count), backend=backend)
            stack.run(velocity)
            row[f"stack{count}_{backend}"] = median_ms(lambda: stack.run(velocity), repeats)
    integrators = {"today": TodayFrame(params, velocity)}
    integrators |= {name: GridCellIntegrator(params, decoder=name, velocity_scale=scale, heading0=HEADING) for name in DECODERS}
    for key, options in (("calibrated1", {}), ("calibrated3", {"modules": 3}), ("calibrated3_ring", {"modules": 3, "heading": "ring"})):
        integrators[key] = GridCellIntegrator(params, decoder="calibrated", velocity_scale=scale, heading0=HEADING, calibration_cache=False,
                                              calibration_grid=TIMING_GRID, **options)
    for integrator in integrators.values():
        for _ in range(3):  # the first frame only stores the pattern; warm the caches
            integrator.step(SPEED, 0.0, 0.0)
    # Interleaved, so that a change of the machine's load touches all alike.
    timed = {name: ([], []) for name in integrators}
    for _ in range(repeats):
        for name, integrator in integrators.items():
            if name == "paper" and len(timed[name][0]) >= slow_repeats:
                continue
            wall, cpu = median_ms(lambda: integrator.step(SPEED, 0.0, 0.0), 1)
            timed[name][0].append(wall)
            timed[name][1].append(cpu)
    for name, (wall, cpu) in timed.items():
        row[name] = (statistics.median(wall), statistics.median(cpu))
    network = GridNetwork(params, dtype=np.float64)
    previous = network.run(velocity)
    field = network.run(velocity)
    row["brute_force"] = median_ms(lambda: decode_paper_bruteforce(previous, field), slow_repeats)
    return row


ROWS = (
    ("network32", "network, 50 steps, GridNetwork float32 (today's)"),
    ("network64", "network, 50 steps, GridNetwork float64"),
    ("full_sheet", "network, 50 steps, authors' full-sheet formulation (float64)"),
    ("stack1_fftw", "network, 50 steps, NetworkStack, 1 module, FFTW"),
    ("stack3_fftw", "network, 50 steps, NetworkStack, 3 modules, FFTW"),
    ("stack1_scipy", "network, 50 steps, NetworkStack, 1 module, scipy.fft"),
    ("stack3_scipy", "network, 50 steps, NetworkStack, 3 modules, scipy.fft"),
    ("today", "whole frame, `subpixel` on GridNetwork float32 (today's formulation)"),
    ("fft", "whole frame, `fft` decoder"),
    ("subpixel", "whole frame, `subpixel` decoder"),
    ("calibrated1", "whole frame, `calibrated`, 1 module"),
    ("calibrated3", "whole frame, `calibrated`, 3 modules"),
    ("calibrated3_ring", "whole frame, `calibrated`, 3 modules, ring heading"),
    ("paper", "whole frame, `paper` decoder"),
    ("brute_force", "`paper` search as the authors wrote it (361 SVDs), alone"),
)
RATIOS = (("calibrated1", "today"), ("calibrated3", "today"), ("subpixel", "today"))


def direction_sweep(directions: int = 24, shift: float = 3.0, settle: int = 12, frames: int = 12) -> list[tuple[float, float, float, float]]:
    """The issue's constant-velocity sweep: the default network from its warm state driven in
    each of ``directions`` directions at ``shift`` neurons per frame (nominal); after ``settle``
    frames, the mean direction error over ``frames`` frames of the raw `subpixel` shift and of
    the `calibrated` decoder (degrees), and the calibrated speed over the input's. All
    directions run as one batch."""
    params = NetworkParams()
    table = flow_table(params)
    angles = 2 * math.pi * np.arange(directions) / directions
    speed = shift / (LATTICE_RATE * params.alpha * params.steps_per_frame)
    velocities = speed * np.exp(1j * angles)
    batch = NetworkStack((params,) * directions, settle=False)
    batch.state = np.repeat(table.warm_state[None], directions, axis=0)
    batch.set_field(np.repeat(table.warm_field[None], directions, axis=0))
    inverters = [LagInverter(table) for _ in range(directions)]
    previous = batch.fields
    raw, calibrated = np.zeros(directions, dtype=complex), np.zeros(directions, dtype=complex)
    for frame in range(settle + frames):
        fields = batch.run(np.column_stack([velocities.real, velocities.imag]))
        for j in range(directions):
            dx, dy = decode_subpixel(previous[j], fields[j], table.search)
            decoded = inverters[j](complex(dx, -dy))
            if frame >= settle:
                raw[j] += complex(dx, -dy)
                calibrated[j] += decoded
        previous = fields
    errors = lambda values: np.degrees(np.angle(values / velocities))  # noqa: E731
    return list(zip(np.degrees(angles), errors(raw), errors(calibrated), np.abs(calibrated / frames / velocities)))


def lag_sweep(drives=(0.02, 0.05, 0.1, 0.15, 0.2), frames: int = 300) -> list[tuple[float, float, float, float]]:
    """The one-frame lag of the default network's flow (calibration.lag_components) on the
    calibration's check sequence around each drive α|v|: (drive, mean flow in neurons per
    frame, lag along, lag across)."""
    table = flow_table(NetworkParams())
    rows = []
    for drive in drives:
        velocities = check_velocities(frames, drive / table.params.alpha)
        measured = check_flows(table, velocities)
        rows.append((drive, float(np.abs(measured).mean()), *lag_components(table, velocities, measured)))
    return rows


def ring_sweep(rates_deg=(1, 2, 5, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100, 120, 150, 180), frames: int = 50
               ) -> list[tuple[float, float, float]]:
    """The largest heading error (degrees) over ``frames`` frames of a constant yaw rate
    (degrees per frame) from rest: of the ring alone, one ring frame per frame (its own
    limit), and of RingHeading, which splits a yaw beyond 30° over several ring frames."""
    calibration = ring_calibration()
    result = []
    for rate in rates_deg:
        ring, heading_model, summed, worst, worst_model = HeadDirectionRing(), RingHeading(0.0), 0.0, 0.0, 0.0
        for _ in range(frames):
            ring.run(calibration.tilt_for(math.radians(rate))[0])
            heading, _ = heading_model.step(math.radians(rate))
            summed += math.radians(rate)
            worst = max(worst, abs(math.degrees(math.remainder(ring.heading - summed, 2 * math.pi))))
            worst_model = max(worst_model, abs(math.degrees(math.remainder(heading - summed, 2 * math.pi))))
        result.append((float(rate), worst, worst_model))
    return result


def print_sweeps() -> None:
    rows = direction_sweep()
    print("Constant velocity, 3 neurons per frame (nominal), default network from its warm state: mean direction error "
          "over frames 13-24, degrees\n")
    print("| direction | `subpixel` | `calibrated` | calibrated speed / input |\n|---:|---:|---:|---:|")
    for angle, raw, calibrated, ratio in rows:
        print(f"| {angle:.0f}° | {raw:+.3f} | {calibrated:+.4f} | {ratio:.5f} |")
    print(f"| largest \\|error\\| | {max(abs(r[1]) for r in rows):.3f} | {max(abs(r[2]) for r in rows):.4f} | "
          f"{max(abs(r[3] - 1) for r in rows):.5f} |\n")
    print("One-frame lag of the flow on the calibration's check sequence (300 frames) around each drive: the fraction of a "
          "change of speed (along) and of a turn (across) that shows a frame late\n")
    print("| α\\|v\\| | mean flow, neurons per frame | along | across |\n|---:|---:|---:|---:|")
    for drive, flow, along, across in lag_sweep():
        print(f"| {drive:g} | {flow:.2f} | {along:.4f} | {across:.4f} |")
    print()
    ring = ring_sweep()
    print("Head-direction ring: largest heading error over 50 frames of a constant yaw rate from rest\n")
    print("| yaw per frame | the ring, one ring frame per frame | `--heading ring` (≤ 30° per ring frame) |\n|---:|---:|---:|")
    for rate, worst, worst_model in ring:
        print(f"| {rate:g}° | {worst:.3f}° | {worst_model:.3f}° |")
    followed = [rate for rate, worst, _ in ring if worst < 1.0]
    print(f"\nlargest rate followed within 1°: {max(followed) if followed else 0:g}° per frame "
          f"(the ring's range: {math.degrees(ring_calibration().max_turn):.1f}° per frame)")
    still = []
    for start in (0.3, 1.0, 2.5):  # at rest: the bump settles onto the cells (half a spacing at most)
        ring = RingHeading(start)
        for _ in range(1000):
            heading, _ = ring.step(0.0)
        still.append(abs(math.degrees(math.remainder(heading - start, 2 * math.pi))))
    print(f"at rest for 1000 frames, from headings 0.3, 1.0, 2.5 rad: moved by {', '.join(f'{d:.3f}°' for d in still)}")


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench gridcells", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="64,128,256", help="comma-separated network sizes n")
    parser.add_argument("--repeats", type=int, default=40, help="frames timed per configuration")
    parser.add_argument("--slow-repeats", type=int, default=8, help="frames timed for the paper decoders")
    parser.add_argument("--sweep", action="store_true",
                        help="instead of timings: the constant-velocity direction sweep (24 directions, raw and calibrated), "
                             "the flow's one-frame lag by speed and the ring attractor's yaw-rate sweep")
    args = parser.parse_args(argv)
    if args.sweep:
        print_sweeps()
        return 0
    sizes = [int(size) for size in args.sizes.split(",")]
    load_before = " ".join(f"{x:.2f}" for x in os.getloadavg())
    rows = {n: measure(n, args.repeats, args.slow_repeats) for n in sizes}
    print(f"Grid-cell integrator: ms per camera frame, wall clock / thread CPU time, medians of {args.repeats} "
          f"frames ({args.slow_repeats} for the paper decoders); load average before {load_before}, after "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}; FFT backend of the fast network: {fft_backend()}\n")
    growth = [f"{a}→{b}" for a, b in zip(sizes, sizes[1:])]
    print("| ms per frame | " + " | ".join(f"n={n}" for n in sizes) + "".join(f" | growth {g} (CPU)" for g in growth) + " |")
    print("|---|" + "---:|" * (len(sizes) + len(growth)))
    for key, title in ROWS:
        if key not in rows[sizes[0]]:
            continue
        cells = [f"{rows[n][key][0]:.2f} / {rows[n][key][1]:.2f}" for n in sizes]
        cells += [f"{rows[b][key][1] / rows[a][key][1]:.1f}×" for a, b in zip(sizes, sizes[1:])]
        print(f"| {title} | " + " | ".join(cells) + " |")
    cells = [f"{rows[n]['settle_s']:.2f} s" for n in sizes] + [f"{rows[b]['settle_s'] / rows[a]['settle_s']:.1f}×" for a, b in zip(sizes, sizes[1:])]
    print("| settling, once per process (wall) | " + " | ".join(cells) + " |")
    print()
    print("| ratio of medians (wall clock), same run | " + " | ".join(f"n={n}" for n in sizes) + " |")
    print("|---|" + "---:|" * len(sizes))
    for key, base in RATIOS:
        print(f"| {key} / {base} | " + " | ".join(f"{rows[n][key][0] / rows[n][base][0]:.2f}" for n in sizes) + " |")
    return 0
