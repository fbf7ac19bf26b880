"""Offline ego-motion: run a frame source through an estimator in one process (no Zenoh),
dead-reckon the increments, score them against ground truth or a reference, and write a
results folder (kiss-icp's pipeline shape: run, evaluate, write poses, config, metrics).

    result = odometry(source, estimator, out=folder)   # structured; writes the folder when given
    result, folder = run_offline("stereo:../shared/data/nubot_scene1", preset="nubot")  # what the CLI runs
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from services.common.errors import DataError
from services.egomotion.base import Estimator, EstimatorConfigError, Increment
from services.evaluation.metrics import MetricsError, ate, end_to_start_gap, endpoint_error, frame_errors
from services.evaluation.plots import plot_series, plot_trajectories
from services.evaluation.results import write_config, write_json, write_trajectory_files
from services.evaluation.trajectory import (
    Trajectory,
    camera_to_planar,
    integrate_increments,
    planar_increments,
    read_kitti,
    read_tum,
)

logger = logging.getLogger(__name__)

# A frame whose increment has less quality than this counts as a failed frame in the metrics.
LOW_QUALITY = 0.1


@dataclass
class OdometryResult:
    """Everything a run produced, one row per processed frame."""

    estimator: str
    seqs: np.ndarray  # (N,) frame indices in the dataset
    stamps: np.ndarray  # (N,) seconds
    increments: np.ndarray  # (N, 3) forward m, left m, yaw rad (body frame of the previous frame)
    quality: np.ndarray  # (N,)
    inliers: np.ndarray  # (N,)
    match_cost: np.ndarray  # (N,)
    seconds: np.ndarray  # (N,) wall time of each estimate() call
    scaled: bool  # False when any increment lacks metric scale
    trajectory: Trajectory  # dead-reckoned planar trajectory (x forward, y left at the start)
    covariances: np.ndarray | None = None  # (N, 3, 3) of each increment, from the estimator's noise model
    ground_truth: Trajectory | None = None  # planar, re-anchored at the first frame
    reference: Trajectory | None = None  # planar, re-anchored at the first frame
    reference_label: str = "reference"
    metrics: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.seqs)


def odometry(
    source: Iterable[Any],
    estimator: Estimator,
    *,
    reference: Trajectory | None = None,
    reference_label: str = "reference",
    progress: Callable[[int, Increment], None] | None = None,
    out: Path | None = None,
    config: dict[str, Any] | None = None,
) -> OdometryResult:
    """Run ``estimator`` over every frame of ``source`` and evaluate the result; with ``out``
    also write the results folder there (`write_results`, ``config`` into config.json).

    ``reference`` is an optional planar trajectory indexed by frame seq (row k is the pose of
    dataset frame k), e.g. another odometry's output, scored like ground truth. Frames'
    own ground truth, when every frame has it, is scored too.
    """
    rows: list[tuple[int, float, Increment, float]] = []
    poses: list[np.ndarray | None] = []
    covariances: list[np.ndarray] = []
    for frame in source:
        start = time.perf_counter()
        increment = estimator.estimate(frame)
        elapsed = time.perf_counter() - start
        rows.append((int(frame.seq), float(frame.stamp), increment, elapsed))
        covariance = estimator.params.covariance(increment) if hasattr(estimator.params, "covariance") else None
        covariances.append(np.full((3, 3), np.nan) if covariance is None else covariance)
        poses.append(None if frame.ground_truth is None else np.asarray(frame.ground_truth, dtype=float))
        if progress is not None:
            progress(len(rows), increment)
        if len(rows) % 100 == 0:
            logger.info("%s: %d frames", estimator.name, len(rows))
    if not rows:
        raise DataError("the source yielded no frames")

    seqs = np.array([row[0] for row in rows])
    stamps = np.array([row[1] for row in rows])
    increments = np.array([(r[2].forward, r[2].left, r[2].yaw) for r in rows], dtype=float)
    trajectory = integrate_increments(increments[:, 0], increments[:, 1], increments[:, 2], stamps)
    ground_truth = None
    if all(pose is not None for pose in poses):
        ground_truth = _anchored(camera_to_planar(Trajectory.from_matrices(stamps, np.stack(poses))))
    selected_reference = None
    if reference is not None:
        if seqs.max() >= len(reference):
            raise DataError(f"the {reference_label} has {len(reference)} poses but frame {seqs.max()} was processed")
        selected = reference.select(seqs)
        selected_reference = _anchored(Trajectory(stamps, selected.positions, selected.quaternions))
    result = OdometryResult(
        estimator=estimator.name,
        seqs=seqs,
        stamps=stamps,
        increments=increments,
        quality=np.array([r[2].quality for r in rows]),
        inliers=np.array([r[2].inliers for r in rows]),
        match_cost=np.array([r[2].match_cost for r in rows]),
        seconds=np.array([r[3] for r in rows]),
        scaled=all(r[2].scaled for r in rows),
        trajectory=trajectory,
        covariances=np.array(covariances),
        ground_truth=ground_truth,
        reference=selected_reference,
        reference_label=reference_label,
    )
    result.metrics = evaluate(result)
    if out is not None:
        write_results(result, out, config if config is not None else estimator_config(estimator))
    return result


def run_offline(
    spec: str,
    *,
    estimator: str | None = None,
    preset: str | None = None,
    config_file: str | Path | None = None,
    calibration: str | Path | None = None,
    start: int = 0,
    stop: int | None = None,
    step: int = 1,
    n_frames: int | None = None,
    reference: str | Path | None = None,
    out: Path | None = None,
    results_root: Path = Path("results"),
    world: dict | None = None,
    topics: dict | None = None,
    shard_block: int | None = None,
) -> tuple[OdometryResult, Path]:
    """Open the source ``spec``, build the estimator from the preset and config file, run
    `odometry` and write the results folder (``out``, or results/<timestamp>/ with a
    ``latest`` link). Returns the result and the folder. What `gridslam odometry` runs.
    ``world``: synthetic world settings over the preset's. ``shard_block``: run the estimator in
    blocks of that many frames, as the egomotion service does (shards.py), for the increments a
    pipeline publishes."""
    from services.common.config import is_preset_file, preset_applies
    from services.egomotion import ESTIMATORS, make_estimator, preset_names, resolve_estimator
    from services.evaluation.results import results_dir
    from services.source import spec as source_spec

    if preset is not None and is_preset_file(preset):
        estimator_preset = preset if preset_applies("egomotion", preset) else None
        source_preset = preset if preset_applies("source", preset) else None
    elif preset is not None and preset not in preset_names() and preset not in source_spec.preset_names():
        raise EstimatorConfigError(
            f"unknown preset {preset!r} (available: {', '.join(sorted(set(preset_names()) | set(source_spec.preset_names())))})"
        )
    else:
        estimator_preset = preset if preset in preset_names() else None
        source_preset = preset if preset in source_spec.preset_names() else None
    if estimator is not None and estimator not in ESTIMATORS:
        raise EstimatorConfigError(f"unknown estimator {estimator!r} (available: {', '.join(ESTIMATORS)})")
    # As the egomotion service resolves it: defaults < preset < config file < GRIDSLAM_EGOMOTION_* < --estimator
    name, params = resolve_estimator(estimator, estimator_preset, config_file)
    if n_frames is not None:
        if n_frames < 1:
            raise EstimatorConfigError(f"--n-frames must be at least 1, got {n_frames}")
        stop = start + n_frames * step if stop is None else min(stop, start + n_frames * step)
    source = source_spec.open_source(
        spec,
        start=start,
        stop=stop,
        step=step,
        preset=source_preset,
        calibration=calibration,
        mono=name != "stereo",
        world=world,
        topics=topics,   # a ROS bag's topics (source/spec.py)
    )
    estimator_instance = make_estimator(name, getattr(source, "camera", None), params)
    if shard_block is not None:
        from services.egomotion.shards import BlockEstimator

        estimator_instance = BlockEstimator(lambda frame: make_estimator(name, getattr(frame, "camera", None) or source.camera,
                                                                         params),
                                            shard_block, name, estimator_instance.params)
    reference_trajectory = load_reference(reference) if reference is not None else None
    folder = results_dir(out, root=results_root)
    config = {
        "source": spec,
        "preset": preset,
        "config_file": None if config_file is None else str(config_file),
        "calibration": None if calibration is None else str(calibration),
        "start": start,
        "stop": stop,
        "step": step,
        "reference": None if reference is None else str(reference),
        "world": world or {},
        **{key: value for key, value in (topics or {}).items() if value is not None},
        "shard_block": shard_block,
        "camera": None if getattr(source, "camera", None) is None else dataclasses.asdict(source.camera),
        "estimator": estimator_config(estimator_instance),
    }
    try:
        result = odometry(
            source,
            estimator_instance,
            reference=reference_trajectory,
            out=folder,
            config=config,
        )
    finally:
        close = getattr(source, "close", None)
        if close is not None:
            close()
    return result, folder


def _anchored(traj: Trajectory) -> Trajectory:
    """The trajectory expressed in the frame of its first pose (so it starts at the origin,
    heading along x), like a dead-reckoned estimate."""
    matrices = traj.matrices()
    return Trajectory.from_matrices(traj.stamps, np.linalg.inv(matrices[0]) @ matrices)


def evaluate(result: OdometryResult) -> dict[str, Any]:
    """Run statistics, and scores against ground truth and the reference when present."""
    n = len(result)
    total = float(result.seconds.sum())
    metrics: dict[str, Any] = {
        "estimator": result.estimator,
        "frames": n,
        "first_seq": int(result.seqs[0]),
        "last_seq": int(result.seqs[-1]),
        # Gaps in seq beyond the selected step: frames the source could not read.
        "frames_missing": int(np.sum(np.diff(result.seqs) - _step(result.seqs))) if n > 1 else 0,
        "scaled": result.scaled,
        "fps": n / total if total > 0 else float("nan"),
        "frame_ms_median": 1000.0 * float(np.median(result.seconds)),
        "frame_ms_max": 1000.0 * float(np.max(result.seconds)),
        "quality_mean": float(result.quality[1:].mean()) if n > 1 else float("nan"),
        "low_quality_frames": int(np.sum(result.quality[1:] < LOW_QUALITY)),
        "path_length_m": result.trajectory.path_length(),
        "end_to_start_gap_m": end_to_start_gap(result.trajectory),
        "yaw_total_deg": float(np.degrees(result.increments[:, 2].sum())),
    }
    for label, truth in (("ground_truth", result.ground_truth), ("reference", result.reference)):
        if truth is not None:
            metrics[label] = compare(result.trajectory, truth, scaled=result.scaled)
            if label == "reference":
                metrics[label]["label"] = result.reference_label
    if result.ground_truth is not None and result.covariances is not None and n > 1:
        metrics["uncertainty"] = uncertainty(result.increments[1:], np.column_stack(planar_increments(result.ground_truth))[1:],
                                             result.covariances[1:])
    return metrics


def uncertainty(increments: np.ndarray, truth: np.ndarray, covariances: np.ndarray) -> dict[str, Any]:
    """How the noise model's standard deviations compare with the errors per frame: the rms
    error, the median modelled σ and the mean normalised squared error (error² / σ², 1 for a
    calibrated model, below 1 for a cautious one), each for forward, left and yaw."""
    errors = increments - truth
    errors[:, 2] = (errors[:, 2] + np.pi) % (2 * np.pi) - np.pi
    sigma = np.sqrt(np.diagonal(covariances, axis1=1, axis2=2))
    known = np.isfinite(sigma).all(axis=1)
    if not known.any():
        return {}
    return {"rms": np.sqrt((errors ** 2).mean(axis=0)).tolist(), "sigma_median": np.median(sigma[known], axis=0).tolist(),
            "normalised_squared_error": ((errors[known] / sigma[known]) ** 2).mean(axis=0).tolist()}


def _step(seqs: np.ndarray) -> int:
    differences = np.diff(seqs)
    return int(np.min(differences)) if len(differences) else 1


def compare(estimate: Trajectory, truth: Trajectory, *, scaled: bool = True) -> dict[str, Any]:
    """ATE after SE(2) and Sim(3) alignment, per-frame errors (also after a least-squares
    scale for unscaled runs), endpoint error and both path lengths."""
    scores: dict[str, Any] = {"path_length_m": truth.path_length(), "end_to_start_gap_m": end_to_start_gap(truth)}
    estimate_increments, truth_increments = planar_increments(estimate), planar_increments(truth)
    attempts: dict[str, Callable[[], Any]] = {
        "ate_se2": lambda: ate(estimate, truth, align="se2"),
        "ate_sim3": lambda: ate(estimate, truth, align="sim3"),
        "frame_errors": lambda: frame_errors(estimate_increments, truth_increments),
        "endpoint": lambda: endpoint_error(estimate, truth),
    }
    if not scaled:
        attempts["frame_errors_scale_aligned"] = lambda: frame_errors(estimate_increments, truth_increments, scale_align=True)
    for key, attempt in attempts.items():
        try:
            scores[key] = attempt()
        except MetricsError as error:  # e.g. two frames, or no motion at all
            logger.warning("%s not computed: %s", key, error)
            scores[key] = None
    return scores


def load_reference(path: str | Path) -> Trajectory:
    """A reference trajectory indexed by frame: a TUM or KITTI pose file (camera convention,
    flattened to planar), or a CSV of per-frame increments (forward,left,yaw or LIBVISO2's
    table, ../shared/data/README.md) dead-reckoned from the origin."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: reference file not found")
    if path.suffix.lower() == ".csv":
        from services.evaluation.motion_io import load_motion

        motion = load_motion(path, "csv")
        if motion.frame != "body":
            raise DataError(f"{path}: a reference CSV must hold body-frame increments (forward,left,yaw or LIBVISO2)")
        # Row k is the motion into frame k in the previous frame's body frame (LIBVISO2's
        # Tt = inv(Tr) translation and heading change): SE(2) composition, as ours.
        forward, left, yaw = motion.increments.T
        return integrate_increments(forward, left, yaw, motion.stamps)
    if path.suffix.lower() == ".tum":
        return read_tum(path)
    return camera_to_planar(read_kitti(path))


def write_results(result: OdometryResult, folder: Path, config: dict[str, Any]) -> dict[str, Path]:
    """Write the run into ``folder``: egomotion.tum / egomotion.kitti.txt (dead-reckoned),
    groundtruth.* and reference.* when known, increments.csv (per frame), metrics.json,
    config.json and trajectory.png (plus frame_errors.png with ground truth)."""
    folder = Path(folder)
    written: dict[str, Path] = {}
    written["egomotion.tum"], written["egomotion.kitti.txt"] = write_trajectory_files(folder, "egomotion", result.trajectory)
    plotted = {result.estimator: result.trajectory}
    if result.ground_truth is not None:
        written["groundtruth.tum"], _ = write_trajectory_files(folder, "groundtruth", result.ground_truth)
        plotted["ground truth"] = result.ground_truth
    if result.reference is not None:
        written["reference.tum"], _ = write_trajectory_files(folder, "reference", result.reference)
        plotted[result.reference_label] = result.reference
    written["increments.csv"] = _write_increments(folder / "increments.csv", result)
    written["metrics.json"] = write_json(folder / "metrics.json", result.metrics)
    written["config.json"] = write_config(folder / "config.json", config)
    title = f"{result.estimator} odometry, {len(result)} frames" + ("" if result.scaled else " (unscaled)")
    written["trajectory.png"] = plot_trajectories(folder / "trajectory.png", plotted, title=title)
    truth = result.ground_truth if result.ground_truth is not None else result.reference
    if truth is not None and len(result) > 1:
        estimate, reference = planar_increments(result.trajectory), planar_increments(truth)
        written["yaw.png"] = plot_series(
            folder / "yaw.png",
            {
                result.estimator: (result.seqs, np.degrees(estimate[2])),
                "ground truth" if result.ground_truth is not None else result.reference_label: (result.seqs, np.degrees(reference[2])),
            },
            xlabel="frame",
            ylabel="yaw per frame [deg]",
            title="rotation per frame",
        )
    return written


def _write_increments(path: Path, result: OdometryResult) -> Path:
    header = "seq,stamp,forward,left,yaw,quality,inliers,match_cost,ms"
    table = np.column_stack(
        (result.seqs, result.stamps, result.increments, result.quality, result.inliers, result.match_cost, 1000 * result.seconds)
    )
    np.savetxt(path, table, delimiter=",", header=header, comments="", fmt=["%d", "%.6f"] + ["%.9g"] * 7)
    return path


def estimator_config(estimator: Estimator) -> dict[str, Any]:
    """The resolved parameters of an estimator, for config.json."""
    params = getattr(estimator, "params", None)
    return {"name": estimator.name, "params": dataclasses.asdict(params) if dataclasses.is_dataclass(params) else {}}


def summary_rows(result: OdometryResult) -> list[tuple[str, Any, str]]:
    """The Metric | Value | Unit rows the command prints."""
    m = result.metrics
    length_unit = "m" if result.scaled else "units"
    rows: list[tuple[str, Any, str]] = [
        ("estimator", result.estimator, ""),
        ("frames", m["frames"], ""),
        ("frames missing", m["frames_missing"], ""),
        ("speed", m["fps"], "frames/s"),
        ("time per frame (median)", m["frame_ms_median"], "ms"),
        ("low-quality frames", m["low_quality_frames"], f"quality < {LOW_QUALITY}"),
        ("path length", m["path_length_m"], length_unit),
        ("end-to-start gap", m["end_to_start_gap_m"], length_unit),
        ("total yaw", m["yaw_total_deg"], "deg"),
    ]
    for label in ("ground_truth", "reference"):
        scores = m.get(label)
        if not scores:
            continue
        name = "ground truth" if label == "ground_truth" else scores.get("label", "reference")
        rows.append((f"{name} path length", scores["path_length_m"], "m"))
        for key, text in (("ate_se2", "ATE RMSE, SE(2)"), ("ate_sim3", "ATE RMSE, Sim(3)")):
            if scores.get(key):
                rows.append((f"{text} vs {name}", scores[key]["rmse"], "m"))
        if scores.get("ate_sim3"):
            rows.append((f"Sim(3) scale vs {name}", scores["ate_sim3"]["scale"], ""))
        for key, suffix in (("frame_errors", ""), ("frame_errors_scale_aligned", ", scale-aligned")):
            errors = scores.get(key)
            if errors:
                rows.append((f"rotation error per frame, median{suffix}", errors["rot_median_deg"], "deg"))
                rows.append((f"rotation error per frame, RMSE{suffix}", errors["rot_rmse_deg"], "deg"))
                rows.append((f"translation error per frame, median{suffix}", errors["trans_median"], "m"))
                rows.append((f"translation error per frame, RMSE{suffix}", errors["trans_rmse"], "m"))
        if scores.get("endpoint"):
            rows.append((f"endpoint error vs {name}", scores["endpoint"]["metres"], "m"))
    for what, key, unit in (("error per frame, rms", "rms", "m, m, rad"), ("noise model σ, median", "sigma_median", "m, m, rad"),
                            ("normalised squared error", "normalised_squared_error", "1: calibrated")):
        values = m.get("uncertainty", {}).get(key)
        if values:
            rows.append((f"{what} (forward, left, yaw)", ", ".join(f"{v:.3g}" for v in values), unit))
    return rows
