"""Trajectory metrics: alignment, ATE, RPE, KITTI drift, endpoint error, per-frame errors.

All functions take an estimate and a reference of the same length, pose k of one matching
pose k of the other (use `associate` first when the stamps differ), and return plain dicts
of floats ready for metrics.json. Positions are in metres, angles in degrees unless the
key says otherwise. Definitions follow:
- alignment: Umeyama, "Least-squares estimation of transformation parameters between two
  point patterns", IEEE TPAMI 13(4), 1991 (eqs. 34-43);
- ATE and RPE: Sturm et al., "A benchmark for the evaluation of RGB-D SLAM systems",
  IROS 2012 (sec. VI), with RPE taken over a fixed travelled distance rather than a time
  step, as in Zhang & Scaramuzza, "A tutorial on quantitative trajectory evaluation for
  visual(-inertial) odometry", IROS 2018 (sec. IV-B);
- drift: the KITTI odometry devkit's definition (Geiger et al., CVPR 2012): segments of
  100..800 m starting every 10 frames, errors divided by segment length, averaged.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from services.common.errors import DataError
from services.common.geometry import wrap
from services.evaluation.trajectory import Trajectory, planar_increments

log = logging.getLogger(__name__)

ALIGNMENTS = ("se2", "se3", "sim3", "none")
KITTI_SEGMENT_LENGTHS_M = tuple(range(100, 900, 100))
KITTI_SEGMENT_STEP_FRAMES = 10


class MetricsError(DataError):
    """The inputs of a metric do not fit together (lengths, too few poses, no motion)."""


# --- helpers --------------------------------------------------------------------------------
def _check_pair(est: Trajectory, ref: Trajectory, minimum: int = 1) -> int:
    if len(est) != len(ref):
        raise MetricsError(
            f"estimate has {len(est)} poses but reference has {len(ref)}: they must match pose for pose "
            "(associate them by timestamp first)"
        )
    if len(ref) < minimum:
        raise MetricsError(f"need at least {minimum} poses, got {len(ref)}")
    return len(ref)


def statistics(errors) -> dict[str, float]:
    """rmse, mean, median, max, std of a set of non-negative errors (NaN when empty)."""
    errors = np.asarray(errors, dtype=float).reshape(-1)
    if errors.size == 0:
        return {key: math.nan for key in ("rmse", "mean", "median", "max", "std")}
    return {
        "rmse": float(np.sqrt(np.mean(errors**2))),
        "mean": float(np.mean(errors)),
        "median": float(np.median(errors)),
        "max": float(np.max(errors)),
        "std": float(np.std(errors)),
    }


def rotation_angles(rotations: np.ndarray) -> np.ndarray:
    """Rotation angle (rad, in [0, pi]) of each (…, 3, 3) rotation matrix.

    atan2(|axis·sin|, cos) rather than arccos((trace-1)/2): arccos loses half the digits
    near zero, where per-frame errors live.
    """
    cos_angle = (np.trace(rotations, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = rotations - np.swapaxes(rotations, -1, -2)
    sin_angle = np.linalg.norm(np.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], axis=-1), axis=-1) / 2.0
    return np.arctan2(sin_angle, cos_angle)


def _relative(matrices: np.ndarray, first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Motions T_first⁻¹ · T_last, vectorised over index pairs."""
    return np.linalg.inv(matrices[first]) @ matrices[last]


def _pair_errors(est: Trajectory, ref: Trajectory, first: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (rad) of E = (ref motion)⁻¹ · (est motion) per pair."""
    if len(first) == 0:
        return np.zeros(0), np.zeros(0)
    error = np.linalg.inv(_relative(ref.matrices(), first, last)) @ _relative(est.matrices(), first, last)
    return np.linalg.norm(error[:, :3, 3], axis=1), rotation_angles(error[:, :3, :3])


# --- alignment ------------------------------------------------------------------------------
def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Rotation R, translation t and scale s minimising Σ‖target − (s R source + t)‖²
    over point sets (n, d), by Umeyama 1991 eqs. 38-42. Points in any dimension d."""
    n, dim = source.shape
    mean_source, mean_target = source.mean(axis=0), target.mean(axis=0)
    centred_source, centred_target = source - mean_source, target - mean_target
    covariance = centred_target.T @ centred_source / n  # eq. 38
    u, d, vt = np.linalg.svd(covariance)
    sign = np.ones(dim)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:  # eq. 43: a reflection is not a rotation
        sign[-1] = -1.0
    rotation = u @ np.diag(sign) @ vt  # eq. 40
    scale = 1.0
    if with_scale:
        variance_source = np.mean(np.sum(centred_source**2, axis=1))  # eq. 36
        if variance_source < 1e-18:
            raise MetricsError("cannot estimate a scale: the estimated trajectory does not move")
        scale = float(np.sum(d * sign) / variance_source)  # eq. 42
    translation = mean_target - scale * rotation @ mean_source  # eq. 41
    return rotation, translation, scale


def apply_transform(traj: Trajectory, rotation: np.ndarray, translation: np.ndarray, scale: float = 1.0) -> Trajectory:
    """The trajectory moved by p' = s R p + t, orientations R R_i (scale leaves them)."""
    matrices = traj.matrices()
    matrices[:, :3, :3] = rotation @ matrices[:, :3, :3]
    matrices[:, :3, 3] = scale * traj.positions @ rotation.T + translation
    return Trajectory.from_matrices(traj.stamps, matrices)


def align(est: Trajectory, ref: Trajectory, kind: str = "se2") -> tuple[Trajectory, dict]:
    """Align `est` onto `ref` by least squares over positions.

    kind: "se2" rotation about z plus x, y translation (planar runs); "se3" rotation and
    translation; "sim3" also a scale (monocular, unscaled runs); "none" leaves it.
    Returns the aligned estimate and {kind, scale, yaw_deg, rotation (3×3), translation}.
    """
    if kind not in ALIGNMENTS:
        raise MetricsError(f"unknown alignment {kind!r}: use one of {', '.join(ALIGNMENTS)}")
    _check_pair(est, ref)
    rotation, translation, scale = np.eye(3), np.zeros(3), 1.0
    if kind == "se2":
        rotation_2d, translation_2d, _ = umeyama(est.positions[:, :2], ref.positions[:, :2], with_scale=False)
        rotation[:2, :2] = rotation_2d
        translation[:2] = translation_2d
    elif kind in ("se3", "sim3"):
        rotation, translation, scale = umeyama(est.positions, ref.positions, with_scale=kind == "sim3")
    aligned = est if kind == "none" else apply_transform(est, rotation, translation, scale)
    params = {
        "kind": kind,
        "scale": float(scale),
        "yaw_deg": float(np.degrees(math.atan2(rotation[1, 0], rotation[0, 0]))),
        "rotation": rotation.tolist(),
        "translation": translation.tolist(),
    }
    return aligned, params


# The metrics below take a parameter named `align` (the contract's keyword), which hides
# the function inside them.
_align = align


def associate(est: Trajectory, ref: Trajectory, max_dt: float = 0.01) -> tuple[Trajectory, Trajectory]:
    """Pairs of poses whose stamps differ by at most `max_dt` s (nearest reference stamp,
    each reference pose used once), for estimates with dropped frames or other rates."""
    if len(est) == 0 or len(ref) == 0:
        raise MetricsError("cannot associate an empty trajectory")
    order = np.argsort(ref.stamps, kind="stable")
    sorted_stamps = ref.stamps[order]
    right = np.clip(np.searchsorted(sorted_stamps, est.stamps), 1, len(ref) - 1) if len(ref) > 1 else np.zeros(len(est), int)
    left = np.maximum(right - 1, 0)
    nearest = np.where(np.abs(sorted_stamps[left] - est.stamps) <= np.abs(sorted_stamps[right] - est.stamps), left, right)
    ref_index = order[nearest]
    keep = np.abs(ref.stamps[ref_index] - est.stamps) <= max_dt
    est_index = np.flatnonzero(keep)
    _, first_use = np.unique(ref_index[est_index], return_index=True)
    est_index = np.sort(est_index[first_use])
    if len(est_index) == 0:
        raise MetricsError(f"no estimated pose lies within {max_dt} s of a reference pose")
    if len(est_index) < len(est):
        log.info("associated %d of %d estimated poses with the reference", len(est_index), len(est))
    return est.select(est_index), ref.select(ref_index[est_index])


# --- metrics --------------------------------------------------------------------------------
def position_errors(est: Trajectory, ref: Trajectory, align: str = "se2") -> np.ndarray:
    """Per-pose position error (m) after alignment, the series behind `ate`."""
    aligned, _ = _align(est, ref, align)
    return np.linalg.norm(aligned.positions - ref.positions, axis=1)


def ate(est: Trajectory, ref: Trajectory, align: str = "se2") -> dict[str, float]:
    """Absolute trajectory error (m): position differences after alignment (Sturm 2012).
    Returns rmse, mean, median, max, std and the alignment scale."""
    aligned, params = _align(est, ref, align)
    result = statistics(np.linalg.norm(aligned.positions - ref.positions, axis=1))
    result["scale"] = params["scale"]
    return result


def rpe(est: Trajectory, ref: Trajectory, delta_m: float) -> dict[str, float]:
    """Relative pose error over a travelled distance of `delta_m` (of the reference path).

    For every frame i, j is the first frame at least `delta_m` further along the reference;
    the error of the pair is E = (T_ref,i⁻¹ T_ref,j)⁻¹ (T_est,i⁻¹ T_est,j), its translation
    norm (m) and rotation angle (deg). Independent of any rigid alignment; NaN statistics
    and 0 pairs when the route is shorter than `delta_m`.
    """
    if not delta_m > 0:
        raise MetricsError(f"RPE distance must be positive, got {delta_m}")
    n = _check_pair(est, ref)
    distances = ref.cumulative_distances()
    first = np.arange(n)
    last = np.searchsorted(distances, distances + delta_m, side="left")
    valid = last < n
    translation, rotation = _pair_errors(est, ref, first[valid], last[valid])
    trans, rot = statistics(translation), statistics(np.degrees(rotation))
    return {
        "delta_m": float(delta_m),
        "pairs": int(valid.sum()),
        "trans_rmse": trans["rmse"],
        "trans_mean": trans["mean"],
        "trans_median": trans["median"],
        "trans_max": trans["max"],
        "rot_rmse_deg": rot["rmse"],
        "rot_mean_deg": rot["mean"],
        "rot_median_deg": rot["median"],
        "rot_max_deg": rot["max"],
    }


def kitti_drift(est: Trajectory, ref: Trajectory) -> dict[str, float] | None:
    """KITTI odometry drift: mean over segments of 100, 200, …, 800 m (of the reference
    path, starting every 10 frames) of translation error / length (%) and rotation error /
    length (deg per 100 m). None when no segment fits (route shorter than 100 m)."""
    n = _check_pair(est, ref)
    distances = ref.cumulative_distances()
    starts = np.arange(0, n, KITTI_SEGMENT_STEP_FRAMES)
    first_all, last_all, length_all = [], [], []
    for length in KITTI_SEGMENT_LENGTHS_M:
        # The devkit takes the first frame strictly beyond the segment length.
        last = np.searchsorted(distances, distances[starts] + length, side="right")
        valid = last < n
        first_all.append(starts[valid])
        last_all.append(last[valid])
        length_all.append(np.full(int(valid.sum()), float(length)))
    first, last, lengths = (np.concatenate(parts) for parts in (first_all, last_all, length_all))
    if len(first) == 0:
        return None
    translation, rotation = _pair_errors(est, ref, first, last)
    return {
        "trans_pct": float(np.mean(translation / lengths) * 100.0),
        "rot_deg_per_100m": float(np.mean(np.degrees(rotation) / lengths) * 100.0),
        "segments": int(len(first)),
    }


def endpoint_error(est: Trajectory, ref: Trajectory, align: str = "none") -> dict[str, float]:
    """Distance (m) between the final estimated and reference positions, and that distance
    as a percentage of the reference path length (NaN for a path of zero length)."""
    aligned, _ = _align(est, ref, align)
    metres = float(np.linalg.norm(aligned.positions[-1] - ref.positions[-1]))
    path = ref.path_length()
    return {"metres": metres, "percent_of_path": 100.0 * metres / path if path > 0 else math.nan}


def end_to_start_gap(traj: Trajectory) -> float:
    """Distance (m) from the last position back to the first: the error of a run that
    returns to its start, where no ground truth exists."""
    if len(traj) == 0:
        raise MetricsError("empty trajectory has no end-to-start gap")
    return float(np.linalg.norm(traj.positions[-1] - traj.positions[0]))


def _as_increments(motion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if isinstance(motion, Trajectory):
        return planar_increments(motion)
    array = np.asarray(motion, dtype=float)
    if array.ndim == 2 and array.shape[0] != 3 and array.shape[1] == 3:
        array = array.T
    if array.ndim != 2 or array.shape[0] != 3:
        raise MetricsError(f"increments must be (forward, left, yaw) arrays or an (N, 3) array, got shape {array.shape}")
    return array[0], array[1], array[2]


def frame_error_series(est, ref, scale_align: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-frame errors of the motion between consecutive frames, for frames 1..N-1.

    `est` and `ref` are Trajectories (full 6-DoF relative motions when both are) or
    planar increments (forward, left, yaw), one per frame as `planar_increments` returns
    them (increment 0, the motion into frame 0, is not scored). The error of a frame is
    E = Δ_ref⁻¹ Δ_est: translation ‖t_est − t_ref‖ (m) and rotation angle (deg).
    `scale_align` first scales the estimated translations by the least-squares factor
    s = Σ t_est·t_ref / Σ‖t_est‖² (for unscaled monocular estimates).
    Returns (translation errors, rotation errors in deg, scale).
    """
    if isinstance(est, Trajectory) and isinstance(ref, Trajectory):
        n = _check_pair(est, ref)
        steps = np.arange(n - 1)
        est_motion = _relative(est.matrices(), steps, steps + 1)
        ref_motion = _relative(ref.matrices(), steps, steps + 1)
    else:
        est_inc, ref_inc = _as_increments(est), _as_increments(ref)
        if len(est_inc[0]) != len(ref_inc[0]):
            raise MetricsError(
                f"estimate has {len(est_inc[0])} increments but reference has {len(ref_inc[0])}: they must match frame for frame"
            )
        est_motion, ref_motion = (_planar_motions(*increments) for increments in (est_inc, ref_inc))
    scale = 1.0
    if scale_align:
        numerator = float(np.sum(est_motion[:, :3, 3] * ref_motion[:, :3, 3]))
        denominator = float(np.sum(est_motion[:, :3, 3] ** 2))
        if denominator < 1e-18:
            raise MetricsError("cannot estimate a scale: the estimated motion has no translation")
        scale = numerator / denominator
        est_motion = est_motion.copy()
        est_motion[:, :3, 3] *= scale
    error = np.linalg.inv(ref_motion) @ est_motion
    return np.linalg.norm(error[:, :3, 3], axis=1), np.degrees(rotation_angles(error[:, :3, :3])), scale


def _planar_motions(forward, left, yaw) -> np.ndarray:
    """4×4 motions of increments 1..N-1."""
    forward, left, yaw = forward[1:], left[1:], wrap(yaw[1:])
    motions = np.tile(np.eye(4), (len(forward), 1, 1))
    motions[:, 0, 0] = motions[:, 1, 1] = np.cos(yaw)
    motions[:, 1, 0] = np.sin(yaw)
    motions[:, 0, 1] = -np.sin(yaw)
    motions[:, 0, 3], motions[:, 1, 3] = forward, left
    return motions


def frame_errors(est_increments, ref_increments, scale_align: bool = False) -> dict[str, float]:
    """Statistics of `frame_error_series`: trans_{mean,median,rmse,max} (m per frame),
    rot_{mean,median,rmse,max}_deg, frames scored and the scale applied."""
    translation, rotation, scale = frame_error_series(est_increments, ref_increments, scale_align)
    trans, rot = statistics(translation), statistics(rotation)
    result = {"frames": int(len(translation)), "scale": scale}
    for key in ("mean", "median", "rmse", "max"):
        result[f"trans_{key}"] = trans[key]
        result[f"rot_{key}_deg"] = rot[key]
    return result
