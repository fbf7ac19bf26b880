"""Offline runs of the grid-cell integrator on motion-only data: `integrate` (a file, as
`gridslam integrate` runs it) and `simulate` (the paper's simulation, `gridslam simulate`).

Each returns a structured result (trajectories, metrics) and writes a results folder:
trajectories (TUM), metrics.json, config.json and PNG plots. Nothing here prints.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from services.common.errors import ConfigError
from services.evaluation import metrics as evaluation
from services.evaluation.plots import plot_heatmaps, plot_series, plot_trajectories
from services.evaluation.results import results_dir, write_config, write_json
from services.common.geometry import wrap
from services.evaluation.trajectory import Trajectory, write_tum
from services.gridcells.gridcode import GridCode
from services.gridcells.integrator import DECODER_NAMES, DeadReckoning, GridCellIntegrator, auto_velocity_scale
from services.evaluation.motion_io import MotionInput, add_noise, load_motion
from services.gridcells.network import GridNetwork, NetworkParams
from services.gridcells.simulation import (
    FiringMap,
    Gridness,
    Walk,
    WalkParams,
    autocorrelogram,
    firing_map,
    gridness,
    random_walk,
)

log = logging.getLogger(__name__)

PROGRESS_EVERY = 0.1  # log progress every tenth of a run


# --- running the integrators ------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class IntegrationRun:
    """One integrator over one input: N poses (one per input row), the decoded lattice shifts
    (N, 2) in columns and rows, the frames flagged saturated, and the wall time."""

    name: str
    trajectory: Trajectory
    shifts: np.ndarray
    saturations: int
    seconds: float
    gridcode: Trajectory | None = None  # the position read from the modules' phases (calibrated decoder)

    def shift_stats(self) -> dict:
        """Median and 95th percentile of the decoded lattice shift per frame (neurons) over
        the moving frames: how far the lattice flows, i.e. how coarse an integer shift is."""
        lengths = np.hypot(self.shifts[:, 0], self.shifts[:, 1])
        lengths = lengths[lengths > 0]
        if not len(lengths):
            return {"median_shift_neurons": 0.0, "p95_shift_neurons": 0.0}
        return {"median_shift_neurons": float(np.median(lengths)), "p95_shift_neurons": float(np.percentile(lengths, 95))}


def resolve_velocity_scale(motion: MotionInput, velocity_scale: float | str | None, params: NetworkParams) -> float:
    """`auto` (or None): the integrator's rule on this input's per-frame speeds
    (integrator.auto_velocity_scale: the 95th percentile of the moving frames' speeds moves
    the lattice by 3 neurons per frame); a number: that many network units per metre."""
    if velocity_scale is None or velocity_scale == "auto":
        return auto_velocity_scale(motion.step_lengths(), params)
    try:
        scale = float(velocity_scale)
    except (TypeError, ValueError):
        raise ConfigError(f"velocity scale {velocity_scale!r}: expected 'auto' or a positive number of network units per metre") from None
    if not (math.isfinite(scale) and scale > 0):
        raise ConfigError(f"velocity scale {velocity_scale!r}: expected 'auto' or a positive number of network units per metre")
    return scale


def _network_heading0(motion: MotionInput) -> float:
    """The integrators' start heading, in the world frame they run in (see MotionInput)."""
    return motion.start[2] + motion.network_rotation


def _drive(integrator, motion: MotionInput, name: str) -> IntegrationRun:
    """Feed every row of `motion` to an integrator (GridCellIntegrator or DeadReckoning)
    created with heading0 = _network_heading0(motion)."""
    n = len(motion)
    poses = np.zeros((n, 3))
    shifts = np.zeros((n, 2))
    body = motion.frame == "body"
    increments, heading_input = motion.increments, motion.heading
    rotation = motion.network_rotation
    if rotation and not body:  # world-frame rows are given in the output frame: turn them
        c, s = math.cos(rotation), math.sin(rotation)
        increments = increments @ np.array([[c, s], [-s, c]])
        heading_input = None if heading_input is None else heading_input + rotation
    every = max(1, int(n * PROGRESS_EVERY))
    code = GridCode(integrator.tables, integrator.velocity_scale, integrator.rotations) if getattr(integrator, "tables", ()) else None
    coded = np.zeros(n, dtype=complex)
    started = time.perf_counter()
    for k in range(n):
        if body:
            step = integrator.step(increments[k, 0], increments[k, 1], increments[k, 2])
        else:
            heading = None if heading_input is None else heading_input[k]
            step = integrator.step_world(increments[k, 0], increments[k, 1], heading)
        poses[k] = step.pose.x, step.pose.y, step.pose.heading
        shifts[k] = step.shift
        if code is not None:  # the phases, searched within one module spacing of the integrated position
            coded[k] = code.decode(integrator.network.fields, complex(step.pose.x, step.pose.y))
        if (k + 1) % every == 0 and name != "deadreckoning":
            log.info("%s: frame %d of %d (%.1f ms per frame)", name, k + 1, n, 1000 * (time.perf_counter() - started) / (k + 1))
    seconds = time.perf_counter() - started
    # The integrators start at the origin of their (possibly turned) world frame: turn back
    # and move to the input's start.
    x0, y0, _ = motion.start
    c, s = math.cos(-rotation), math.sin(-rotation)
    x = x0 + c * poses[:, 0] - s * poses[:, 1]
    y = y0 + s * poses[:, 0] + c * poses[:, 1]
    trajectory = Trajectory.from_planar(motion.stamps, x, y, wrap(poses[:, 2] - rotation))
    gridcode = None
    if code is not None:
        gx, gy = x0 + c * coded.real - s * coded.imag, y0 + s * coded.real + c * coded.imag
        gridcode = Trajectory.from_planar(motion.stamps, gx, gy, wrap(poses[:, 2] - rotation))
    return IntegrationRun(name, trajectory, shifts, int(integrator.saturations), seconds, gridcode)


@dataclass(frozen=True)
class GridOptions:
    """The grid-cell integrator's options beside the decoder (GridCellIntegrator): the step
    source, the number of grid modules and the heading model."""

    step: str = "odometry"
    modules: int = 1
    heading: str = "sum"

    def label(self, decoder: str) -> str:
        """A run's name: the decoder, with the options that differ from the defaults."""
        parts = [decoder] + ([f"step-{self.step}"] if self.step != "odometry" else []) + (
            [f"{self.modules}-modules"] if self.modules != 1 else []) + ([f"heading-{self.heading}"] if self.heading != "sum" else [])
        return "+".join(parts)


def run_grid(motion: MotionInput, decoder: str, velocity_scale: float, params: NetworkParams = NetworkParams(),
             options: GridOptions = GridOptions()) -> IntegrationRun:
    """The grid-cell integrator with one decoder over every row of `motion`."""
    integrator = GridCellIntegrator(params, decoder=decoder, velocity_scale=velocity_scale, heading0=_network_heading0(motion),
                                    step=options.step, modules=options.modules, heading=options.heading)
    run = _drive(integrator, motion, options.label(decoder))
    if run.saturations:
        log.warning(
            "%s: the lattice flow saturated in %d of %d frames (velocity scale %.4g units/m): lower --velocity-scale",
            decoder, run.saturations, len(motion), velocity_scale,
        )
    return run


def run_deadreckoning(motion: MotionInput) -> IntegrationRun:
    """The baseline over the same rows, same heading convention."""
    return _drive(DeadReckoning(heading0=_network_heading0(motion)), motion, "deadreckoning")


# --- metrics ----------------------------------------------------------------------------------
def trajectory_metrics(est: Trajectory, reference: Trajectory | None, deadreckoning: Trajectory | None = None) -> dict:
    """Metrics of one trajectory: its length and end-to-start gap always; against the ground
    truth (same frame, same start, no alignment: odometry is judged as it drifts) the
    endpoint error and the mean position error, in metres and in % of the true path length,
    the ATE RMSE and the KITTI drift when the route is long enough; and against dead
    reckoning of the same inputs the endpoint and mean differences (for inputs with no truth)."""
    result = {"path_length_m": est.path_length(), "end_to_start_gap_m": evaluation.end_to_start_gap(est)}
    if reference is not None:
        errors = evaluation.position_errors(est, reference, align="none")
        path = reference.path_length()
        endpoint = evaluation.endpoint_error(est, reference)
        result |= {
            "endpoint_error_m": endpoint["metres"],
            "endpoint_error_pct": endpoint["percent_of_path"],
            "mean_error_m": float(errors.mean()),
            "mean_error_pct": 100.0 * float(errors.mean()) / path if path > 0 else math.nan,
            "max_error_m": float(errors.max()),
            "ate_rmse_m": float(np.sqrt(np.mean(errors**2))),
            "ate_se2_rmse_m": evaluation.ate(est, reference, align="se2")["rmse"] if len(est) >= 3 else math.nan,
        }
        drift = evaluation.kitti_drift(est, reference)
        if drift is not None:
            result |= {"kitti_drift_pct": drift["trans_pct"], "kitti_drift_deg_per_100m": drift["rot_deg_per_100m"]}
    if deadreckoning is not None:
        differences = np.linalg.norm(est.positions - deadreckoning.positions, axis=1)
        result |= {"endpoint_difference_from_dr_m": float(differences[-1]), "mean_difference_from_dr_m": float(differences.mean())}
        result |= direction_errors(est, deadreckoning)
    return result


def direction_errors(est: Trajectory, deadreckoning: Trajectory) -> dict:
    """How the integrator's per-frame displacement and heading differ from dead reckoning of
    the same inputs (its input): the direction of travel per frame (rms and mean, degrees,
    over the frames where both moved; and the rms weighted by the step length, which frames
    of almost no motion, whose direction means little, do not dominate), the step length (mean
    ratio) and the heading (final and largest difference, degrees: the drift of a heading
    model against the summed yaw)."""
    step_est, step_dr = np.diff(est.positions[:, :2], axis=0), np.diff(deadreckoning.positions[:, :2], axis=0)
    moved = (np.hypot(*step_dr.T) > 0) & (np.hypot(*step_est.T) > 0)
    result = {}
    if np.any(moved):
        angle = np.angle((step_est[moved, 0] + 1j * step_est[moved, 1]) / (step_dr[moved, 0] + 1j * step_dr[moved, 1]))
        length = np.hypot(*step_dr[moved].T)
        result |= {"direction_rms_deg": float(np.degrees(np.sqrt(np.mean(angle**2)))),
                   "direction_mean_deg": float(np.degrees(angle.mean())),
                   "direction_weighted_rms_deg": float(np.degrees(np.sqrt(np.sum((length * angle) ** 2) / np.sum(length**2)))),
                   "step_ratio_mean": float(np.mean(np.hypot(*step_est[moved].T) / np.hypot(*step_dr[moved].T)))}
    heading = np.degrees(np.abs(wrap(est.planar()[2] - deadreckoning.planar()[2])))
    result |= {"heading_difference_end_deg": float(heading[-1]), "heading_difference_max_deg": float(heading.max())}
    return result


def gridcode_metrics(run: IntegrationRun, truth: Trajectory | None, deadreckoning: Trajectory) -> dict:
    """The grid-code position (from the modules' phases) scored like the integrated one, and
    how far it is from the integrated position (mean and largest, m)."""
    apart = np.linalg.norm(run.gridcode.positions - run.trajectory.positions, axis=1)
    result = {key: value for key, value in trajectory_metrics(run.gridcode, truth, deadreckoning).items()
              if not key.startswith(("direction", "step_ratio", "heading"))}
    return result | {"mean_difference_from_integrated_m": float(apart.mean()), "max_difference_from_integrated_m": float(apart.max())}


def error_over_time(est: Trajectory, reference: Trajectory) -> np.ndarray:
    """Position error of every pose (m), no alignment: the drift curve of the paper's Fig. 3."""
    return np.linalg.norm(est.positions - reference.positions, axis=1)


# --- integrate --------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class IntegrationResult:
    """What `integrate` computed and where it wrote it."""

    motion: MotionInput
    decoder: str
    velocity_scale: float
    grid: IntegrationRun
    deadreckoning: IntegrationRun
    metrics: dict
    out_dir: Path | None = None
    files: dict[str, Path] = field(default_factory=dict)

    @property
    def groundtruth(self) -> Trajectory | None:
        return self.motion.groundtruth


def integrate(
    path,
    fmt: str | None = None,
    decoder: str = "subpixel",
    velocity_scale: float | str | None = "auto",
    n_frames: int | None = None,
    noise_trans: float = 0.0,
    noise_rot_deg: float = 0.0,
    seed: int = 0,
    network_rotation_deg: float = 0.0,
    params: NetworkParams = NetworkParams(),
    out: Path | None = None,
    results_root: Path = Path("results"),
    write: bool = True,
    options: GridOptions = GridOptions(),
) -> IntegrationResult:
    """Load a motion file, integrate it with the grid cells and with dead reckoning, score
    both (against the ground truth when the input is a trajectory), and write the results
    folder (`out`, or a new results/<timestamp>/) unless `write` is False.

    `network_rotation_deg` turns the world frame the network runs in (results are turned
    back): the integer decoders snap the direction of travel to lattice directions, which
    favours routes aligned with them; turning the frame shows how much of a result is that."""
    if decoder not in DECODER_NAMES:
        raise ConfigError(f"unknown decoder '{decoder}': choose one of {', '.join(DECODER_NAMES)}")
    if not math.isfinite(network_rotation_deg):
        raise ConfigError(f"network rotation {network_rotation_deg}: must be a finite number of degrees")
    motion = load_motion(path, fmt).head(n_frames)
    motion = add_noise(motion, noise_trans, noise_rot_deg, seed)
    motion = replace(motion, network_rotation=motion.network_rotation + math.radians(network_rotation_deg))
    scale = resolve_velocity_scale(motion, velocity_scale, params)
    log.info("integrating %s with the %s decoder, velocity scale %.4g network units per metre", motion.describe(), decoder, scale)
    grid = run_grid(motion, decoder, scale, params, options)
    deadreckoning = run_deadreckoning(motion)
    truth = motion.groundtruth
    metrics = {
        "input": {
            "path": str(motion.path),
            "format": motion.format,
            "layout": motion.layout,
            "frame": motion.frame,
            "frames": len(motion),
            "noise_trans": noise_trans,
            "noise_rot_deg": noise_rot_deg,
            "seed": seed,
            "network_rotation_deg": math.degrees(motion.network_rotation),
        },
        "decoder": decoder,
        "step": options.step,
        "modules": options.modules,
        "heading": options.heading,
        "velocity_scale": scale,
        "saturations": grid.saturations,
        "seconds": grid.seconds,
        "ms_per_frame": 1000.0 * grid.seconds / len(motion),
        "grid": trajectory_metrics(grid.trajectory, truth, deadreckoning.trajectory) | grid.shift_stats(),
        "deadreckoning": trajectory_metrics(deadreckoning.trajectory, truth),
    }
    if grid.gridcode is not None:
        metrics["gridcode"] = gridcode_metrics(grid, truth, deadreckoning.trajectory)
    if truth is not None:
        metrics["groundtruth"] = {"path_length_m": truth.path_length(), "end_to_start_gap_m": evaluation.end_to_start_gap(truth)}
    result = IntegrationResult(motion, decoder, scale, grid, deadreckoning, metrics)
    if not write:
        return result
    folder = results_dir(out, results_root)
    files = write_integration(folder, result, config={
        "input": str(motion.path), "format": fmt, "decoder": decoder, "velocity_scale": velocity_scale,
        "resolved_velocity_scale": scale, "n_frames": n_frames, "noise_trans": noise_trans,
        "noise_rot_deg": noise_rot_deg, "seed": seed, "network_rotation_deg": network_rotation_deg, "network": params,
        "step": options.step, "modules": options.modules, "heading": options.heading,
    })
    return replace(result, out_dir=folder, files=files)


def write_integration(folder: Path, result: IntegrationResult, config: dict) -> dict[str, Path]:
    """trajectory.tum, deadreckoning.tum, groundtruth.tum (when known), metrics.json,
    config.json, trajectories.png and, with ground truth, error.png."""
    files = {
        "trajectory": write_tum(folder / "trajectory.tum", result.grid.trajectory),
        "deadreckoning": write_tum(folder / "deadreckoning.tum", result.deadreckoning.trajectory),
    }
    if result.grid.gridcode is not None:
        files["gridcode"] = write_tum(folder / "gridcode.tum", result.grid.gridcode)
    shown = {}
    truth = result.groundtruth
    if truth is not None:
        files["groundtruth"] = write_tum(folder / "groundtruth.tum", truth)
        shown["groundtruth"] = truth
    shown |= {f"grid cells ({result.grid.name})": result.grid.trajectory, "dead reckoning": result.deadreckoning.trajectory}
    files["metrics"] = write_json(folder / "metrics.json", result.metrics)
    files["config"] = write_config(folder / "config.json", config)
    files["plot"] = plot_trajectories(folder / "trajectories.png", shown, title=f"{result.motion.path.name}: grid cells vs dead reckoning")
    if truth is not None:
        stamps = result.motion.stamps - result.motion.stamps[0]
        files["error_plot"] = plot_series(
            folder / "error.png",
            {
                f"grid cells ({result.grid.name})": (stamps, error_over_time(result.grid.trajectory, truth)),
                "dead reckoning": (stamps, error_over_time(result.deadreckoning.trajectory, truth)),
            },
            xlabel="time [s]", ylabel="position error [m]", title=f"{result.motion.path.name}: drift",
        )
    log.info("wrote %s", folder)
    return files


def integration_table(result: IntegrationResult) -> list[tuple[str, object, str]]:
    """Rows of the Metric | Value | Unit table `gridslam integrate` prints."""
    m = result.metrics
    grid, dr = m["grid"], m["deadreckoning"]
    rows = [
        ("frames", m["input"]["frames"], ""),
        ("decoder", result.grid.name, ""),
        ("velocity scale", result.velocity_scale, "network units/m"),
        ("saturated frames", m["saturations"], "frames"),
        ("median lattice shift", m["grid"]["median_shift_neurons"], "neurons/frame"),
        ("time per frame", m["ms_per_frame"], "ms"),
        ("grid path length", grid["path_length_m"], "m"),
        ("dead-reckoning path length", dr["path_length_m"], "m"),
    ]
    if "groundtruth" in m:
        rows += [
            ("ground-truth path length", m["groundtruth"]["path_length_m"], "m"),
            ("grid endpoint error", grid["endpoint_error_pct"], "% of path"),
            ("grid mean error", grid["mean_error_pct"], "% of path"),
            ("grid ATE RMSE", grid["ate_rmse_m"], "m"),
            ("dead-reckoning endpoint error", dr["endpoint_error_pct"], "% of path"),
            ("dead-reckoning mean error", dr["mean_error_pct"], "% of path"),
        ]
    rows += [
        ("grid end-to-start gap", grid["end_to_start_gap_m"], "m"),
        ("dead-reckoning end-to-start gap", dr["end_to_start_gap_m"], "m"),
        ("grid endpoint difference from DR", grid["endpoint_difference_from_dr_m"], "m"),
        ("grid mean difference from DR", grid["mean_difference_from_dr_m"], "m"),
    ]
    rows += _direction_rows(grid, "grid")
    if "gridcode" in m:
        rows += _gridcode_rows(m["gridcode"], "grid code")
    return rows


def _gridcode_rows(metrics: dict, name: str) -> list[tuple[str, object, str]]:
    rows = [(f"{name}: mean distance from the integrated position", metrics["mean_difference_from_integrated_m"], "m")]
    if "endpoint_error_pct" in metrics:
        rows += [(f"{name}: endpoint error", metrics["endpoint_error_pct"], "% of path"),
                 (f"{name}: mean error", metrics["mean_error_pct"], "% of path")]
    return rows


def _direction_rows(metrics: dict, name: str) -> list[tuple[str, object, str]]:
    rows = []
    if "direction_rms_deg" in metrics:
        rows += [(f"{name} direction vs input, rms", metrics["direction_rms_deg"], "deg/frame"),
                 (f"{name} direction vs input, rms weighted by step", metrics["direction_weighted_rms_deg"], "deg/frame"),
                 (f"{name} direction vs input, mean", metrics["direction_mean_deg"], "deg/frame")]
    return rows + [(f"{name} heading vs summed yaw, end", metrics["heading_difference_end_deg"], "deg"),
                   (f"{name} heading vs summed yaw, max", metrics["heading_difference_max_deg"], "deg")]


# --- simulate ---------------------------------------------------------------------------------
NEURON = (0, 0)  # the neuron whose firing map the paper's Fig. 4 shows


@dataclass(frozen=True, eq=False)
class SimulationResult:
    """What `simulate` computed: the walk, every decoder's run, dead reckoning, the metrics,
    and the long run's firing map with its gridness score."""

    walk: Walk
    motion: MotionInput
    velocity_scale: float
    runs: dict[str, IntegrationRun]
    deadreckoning: IntegrationRun
    metrics: dict
    firing: FiringMap | None
    gridness: Gridness | None
    out_dir: Path | None = None
    files: dict[str, Path] = field(default_factory=dict)


def walk_motion(walk: Walk) -> MotionInput:
    """The walk as body-frame odometry (forward, left, yaw per frame) with its ground truth."""
    truth = Trajectory.from_planar(walk.stamps, walk.positions[:, 0], walk.positions[:, 1], walk.heading)
    start = (float(walk.positions[0, 0]), float(walk.positions[0, 1]), float(walk.heading[0]))
    return MotionInput(Path("simulation"), "simulation", "walk", "body", walk.stamps, walk.body_increments(), start=start, groundtruth=truth)


def neuron_activity(walk: Walk, velocity_scale: float, params: NetworkParams = NetworkParams(), neuron: tuple[int, int] = NEURON) -> np.ndarray:
    """The firing rate r of one neuron after every frame of the walk, the network driven by
    the walk's true world-frame velocity (no decoding is needed for a firing map)."""
    network = GridNetwork(params)
    velocity = np.vstack([[0.0, 0.0], np.diff(walk.positions, axis=0)]) * velocity_scale
    activity = np.empty(len(walk))
    every = max(1, int(len(walk) * PROGRESS_EVERY))
    started = time.perf_counter()
    for k, (vx, vy) in enumerate(velocity):
        network.run((vx, vy))
        activity[k] = network.state[neuron]
        if (k + 1) % every == 0:
            log.info("firing map: frame %d of %d (%.1f ms per frame)", k + 1, len(walk), 1000 * (time.perf_counter() - started) / (k + 1))
    return activity


def simulate(
    n_frames: int = 3500,
    seed: int = 0,
    decoders: tuple[str, ...] = ("paper", "fft", "subpixel"),
    noise_trans: float = 0.0,
    noise_rot_deg: float = 0.0,
    velocity_scale: float | str | None = "auto",
    firing_frames: int = 30000,
    bin_m: float = 0.05,
    walk_params: WalkParams = WalkParams(),
    params: NetworkParams = NetworkParams(),
    out: Path | None = None,
    results_root: Path = Path("results"),
    write: bool = True,
    options: GridOptions = GridOptions(),
) -> SimulationResult:
    """The paper's simulation: a seeded random walk in the circle; every decoder and dead
    reckoning integrate the same (optionally noisy) odometry of its first `n_frames` frames;
    then the walk continued to `firing_frames` frames drives the network alone for the firing
    map of neuron (0, 0) and its gridness (0 frames: no firing map)."""
    unknown = [name for name in decoders if name not in DECODER_NAMES]
    if unknown or not decoders:
        raise ConfigError(f"unknown decoder '{unknown[0] if unknown else ''}': choose from {', '.join(DECODER_NAMES)}")
    if n_frames < 2:
        raise ConfigError(f"the simulation needs at least 2 frames, got {n_frames}")
    if firing_frames < 0:
        raise ConfigError(f"firing-map frames must be >= 0, got {firing_frames}")
    # One walk: its first n_frames frames are the drift run, all of it the firing-map run.
    long_walk = random_walk(max(n_frames, firing_frames), seed, walk_params)
    walk = long_walk.head(n_frames)
    clean = walk_motion(walk)
    motion = add_noise(clean, noise_trans, noise_rot_deg, seed)
    # The scale comes from the noise-free speeds, so every noise level drives the network alike.
    scale = resolve_velocity_scale(clean, velocity_scale, params)
    log.info("simulation: %d frames, %.1f m, velocity scale %.4g network units per metre", n_frames, walk.path_length(), scale)
    truth = clean.groundtruth
    deadreckoning = run_deadreckoning(motion)
    # The step source and modules need the calibrated decoder: the other decoders run with the
    # defaults beside it; the heading model applies to all.
    runs = {}
    for name in decoders:
        own = options if name == "calibrated" else replace(options, step="odometry", modules=1)
        run = run_grid(motion, name, scale, params, own)
        runs[run.name] = run
    metrics = {
        "walk": {
            "frames": n_frames, "seed": seed, "frame_period_s": walk_params.frame_period_s,
            "radius_m": walk_params.radius_m, "max_speed_m_s": walk_params.max_speed_m_s,
            "path_length_m": walk.path_length(), "duration_s": float(walk.stamps[-1]),
            "noise_trans": noise_trans, "noise_rot_deg": noise_rot_deg,
        },
        "velocity_scale": scale,
        "deadreckoning": trajectory_metrics(deadreckoning.trajectory, truth),
    }
    for name, run in runs.items():
        metrics[name] = trajectory_metrics(run.trajectory, truth, deadreckoning.trajectory) | {
            "saturations": run.saturations, "ms_per_frame": 1000.0 * run.seconds / n_frames,
        } | run.shift_stats()
        if run.gridcode is not None:
            metrics[f"{name} gridcode"] = gridcode_metrics(run, truth, deadreckoning.trajectory)
    rate_map, score = None, None
    if firing_frames:
        firing_walk = long_walk.head(firing_frames)
        activity = neuron_activity(firing_walk, scale, params)
        rate_map = firing_map(firing_walk.positions, activity, walk_params.radius_m, bin_m)
        score = gridness(rate_map.rate)
        metrics["firing_map"] = {
            "frames": firing_frames, "neuron": list(NEURON), "bin_m": bin_m,
            "gridness": score.score, "spacing_m": score.spacing_bins * bin_m,
            "rotational_correlations": {str(angle): value for angle, value in score.correlations.items()},
        }
        log.info("firing map of neuron %s over %d frames: gridness %.3f", NEURON, firing_frames, score.score)
    result = SimulationResult(walk, motion, scale, runs, deadreckoning, metrics, rate_map, score)
    if not write:
        return result
    folder = results_dir(out, results_root)
    files = write_simulation(folder, result, config={
        "n_frames": n_frames, "seed": seed, "decoders": list(decoders), "step": options.step, "modules": options.modules,
        "heading": options.heading, "noise_trans": noise_trans,
        "noise_rot_deg": noise_rot_deg, "velocity_scale": velocity_scale, "resolved_velocity_scale": scale,
        "firing_frames": firing_frames, "bin_m": bin_m, "walk": walk_params, "network": params,
    })
    return replace(result, out_dir=folder, files=files)


def write_simulation(folder: Path, result: SimulationResult, config: dict) -> dict[str, Path]:
    """groundtruth.tum, deadreckoning.tum, trajectory_<decoder>.tum, metrics.json,
    config.json, trajectories.png, drift.png (Fig. 3) and firing_map.png (Fig. 4)."""
    truth = result.motion.groundtruth
    files = {
        "groundtruth": write_tum(folder / "groundtruth.tum", truth),
        "deadreckoning": write_tum(folder / "deadreckoning.tum", result.deadreckoning.trajectory),
    }
    for name, run in result.runs.items():
        files[f"trajectory_{name}"] = write_tum(folder / f"trajectory_{name}.tum", run.trajectory)
        if run.gridcode is not None:
            files[f"gridcode_{name}"] = write_tum(folder / f"gridcode_{name}.tum", run.gridcode)
    files["metrics"] = write_json(folder / "metrics.json", result.metrics)
    files["config"] = write_config(folder / "config.json", config)
    shown = {"groundtruth": truth} | {f"grid cells ({name})": run.trajectory for name, run in result.runs.items()}
    shown["dead reckoning"] = result.deadreckoning.trajectory
    files["plot"] = plot_trajectories(folder / "trajectories.png", shown, title="Simulated walk in a circle of radius 2 m")
    stamps = result.walk.stamps
    series = {f"grid cells ({name})": (stamps, 100 * error_over_time(run.trajectory, truth)) for name, run in result.runs.items()}
    series["dead reckoning"] = (stamps, 100 * error_over_time(result.deadreckoning.trajectory, truth))
    files["drift_plot"] = plot_series(folder / "drift.png", series, xlabel="time [s]", ylabel="position error [cm]",
                                      title="Drift over time (paper Fig. 3)")
    if result.firing is not None:
        files["firing_plot"] = plot_heatmaps(
            folder / "firing_map.png",
            {
                f"neuron {NEURON} firing map ({result.metrics['firing_map']['frames']} frames)": result.firing.rate,
                f"autocorrelogram, gridness {result.gridness.score:.2f}": autocorrelogram(result.firing.rate),
            },
            title="Firing map over the arena (paper Fig. 4)", cmap="jet",
        )
    log.info("wrote %s", folder)
    return files


def simulation_table(result: SimulationResult) -> list[tuple[str, object, str]]:
    """Rows of the Metric | Value | Unit table `gridslam simulate` prints."""
    m = result.metrics
    rows = [
        ("frames", m["walk"]["frames"], ""),
        ("path length", m["walk"]["path_length_m"], "m"),
        ("velocity scale", result.velocity_scale, "network units/m"),
        ("dead reckoning endpoint error", m["deadreckoning"]["endpoint_error_pct"], "% of path"),
        ("dead reckoning mean error", m["deadreckoning"]["mean_error_pct"], "% of path"),
    ]
    for name in result.runs:
        rows += [
            (f"{name} endpoint error", m[name]["endpoint_error_pct"], "% of path"),
            (f"{name} mean error", m[name]["mean_error_pct"], "% of path"),
            (f"{name} saturated frames", m[name]["saturations"], "frames"),
            (f"{name} time per frame", m[name]["ms_per_frame"], "ms"),
        ] + _direction_rows(m[name], name)
        if f"{name} gridcode" in m:
            rows += _gridcode_rows(m[f"{name} gridcode"], f"{name} grid code")
    if "firing_map" in m:
        rows += [
            ("firing map frames", m["firing_map"]["frames"], ""),
            (f"gridness of neuron {NEURON}", m["firing_map"]["gridness"], ""),
            ("firing field spacing", m["firing_map"]["spacing_m"], "m"),
        ]
    return rows
