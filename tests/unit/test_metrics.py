"""Metrics against hand-computed cases (and against evo where it happens to be installed)."""

import math

import numpy as np
import pytest

from services.common.errors import DataError
from services.evaluation.metrics import (
    MetricsError,
    align,
    apply_transform,
    associate,
    ate,
    end_to_start_gap,
    endpoint_error,
    frame_error_series,
    frame_errors,
    kitti_drift,
    position_errors,
    rpe,
)
from services.evaluation.trajectory import Trajectory, integrate_increments, planar_increments
from tests.extras import require


def yaw_matrix(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def random_3d(n=40, seed=0) -> Trajectory:
    rng = np.random.default_rng(seed)
    return Trajectory(np.arange(n), np.cumsum(rng.normal(size=(n, 3)), axis=0), rng.normal(size=(n, 4)))


def square(side=10.0, per_side=10) -> Trajectory:
    """Counter-clockwise square from the origin back to it, heading along each side."""
    x, y, yaw = [0.0], [0.0], [0.0]
    corners = [(0, 0), (side, 0), (side, side), (0, side), (0, 0)]
    for (x0, y0), (x1, y1) in zip(corners, corners[1:]):
        heading = math.atan2(y1 - y0, x1 - x0)
        for k in range(1, per_side + 1):
            x.append(x0 + (x1 - x0) * k / per_side)
            y.append(y0 + (y1 - y0) * k / per_side)
            yaw.append(heading)
    return Trajectory.from_planar(np.arange(len(x)), x, y, yaw)


def straight(n, step=1.0, yaw_rate=0.0) -> Trajectory:
    """Along +x, `step` m per frame, heading k·yaw_rate at frame k (positions unaffected)."""
    k = np.arange(n, dtype=float)
    return Trajectory.from_planar(k, k * step, np.zeros(n), k * yaw_rate)


# --- alignment and ATE ----------------------------------------------------------------------
def test_sim3_recovers_a_rotated_translated_scaled_copy():
    ref = random_3d()
    rotation = yaw_matrix(0.7) @ np.array([[1, 0, 0], [0, math.cos(0.4), -math.sin(0.4)], [0, math.sin(0.4), math.cos(0.4)]])
    est = apply_transform(ref, rotation, np.array([5.0, -3.0, 2.0]), scale=0.25)
    aligned, params = align(est, ref, "sim3")
    assert params["scale"] == pytest.approx(4.0)
    assert np.allclose(aligned.positions, ref.positions, atol=1e-9)
    assert np.allclose(aligned.matrices(), ref.matrices(), atol=1e-9)
    result = ate(est, ref, align="sim3")
    assert result["rmse"] < 1e-9 and result["scale"] == pytest.approx(4.0)
    # Without the scale the same copy cannot be aligned.
    assert ate(est, ref, align="se3")["rmse"] > 1.0


def test_se3_aligns_a_rigid_copy_and_keeps_unit_scale():
    ref = random_3d(seed=1)
    est = apply_transform(ref, yaw_matrix(-1.2), np.array([1.0, 2.0, 3.0]))
    result = ate(est, ref, align="se3")
    assert result["rmse"] < 1e-9 and result["scale"] == 1.0


def test_constant_offset_of_one_metre():
    ref = square()
    est = Trajectory(ref.stamps, ref.positions + [0.6, 0.8, 0.0], ref.quaternions)
    none = ate(est, ref, align="none")
    assert none["rmse"] == pytest.approx(1.0) and none["mean"] == pytest.approx(1.0)
    assert none["max"] == pytest.approx(1.0) and none["std"] == pytest.approx(0.0, abs=1e-12)
    assert ate(est, ref, align="se2")["rmse"] == pytest.approx(0.0, abs=1e-9)


def test_se2_undoes_a_yaw_and_shift_and_reports_it():
    ref = square()
    est = apply_transform(ref, yaw_matrix(math.radians(30.0)), np.array([4.0, -2.0, 0.0]))
    aligned, params = align(est, ref, "se2")
    assert params["yaw_deg"] == pytest.approx(-30.0)
    assert np.allclose(aligned.positions, ref.positions, atol=1e-9)
    assert np.allclose(aligned.planar()[2], ref.planar()[2], atol=1e-9)


def test_ate_statistics_by_hand():
    # Errors 0, 0, 0, 2 m: rmse sqrt(4/4) = 1, mean 0.5, median 0, max 2, std sqrt(1 - 0.25).
    ref = straight(4)
    est = Trajectory.from_planar(ref.stamps, [0, 1, 2, 3], [0, 0, 0, 2], np.zeros(4))
    result = ate(est, ref, align="none")
    assert result["rmse"] == pytest.approx(1.0)
    assert result["mean"] == pytest.approx(0.5)
    assert result["median"] == pytest.approx(0.0)
    assert result["max"] == pytest.approx(2.0)
    assert result["std"] == pytest.approx(math.sqrt(0.75))
    assert np.allclose(position_errors(est, ref, align="none"), [0, 0, 0, 2])


def test_alignment_never_reflects():
    # A mirror image (y -> -y) is best matched by a reflection; a rotation must be returned.
    ref = square()
    est = Trajectory.from_planar(ref.stamps, ref.positions[:, 0], -ref.positions[:, 1], -ref.planar()[2])
    for kind in ("se2", "se3", "sim3"):
        _, params = align(est, ref, kind)
        assert np.linalg.det(np.array(params["rotation"])) == pytest.approx(1.0)
    assert ate(est, ref, align="se2")["rmse"] > 1.0


def test_sim3_of_a_still_estimate_is_a_clear_error():
    ref = straight(5)
    est = Trajectory.from_planar(ref.stamps, np.zeros(5), np.zeros(5), np.zeros(5))
    with pytest.raises(MetricsError, match="does not move"):
        ate(est, ref, align="sim3")


def test_unknown_alignment_and_length_mismatch_are_clear_errors():
    ref = straight(5)
    with pytest.raises(MetricsError, match="unknown alignment 'se4'"):
        align(ref, ref, "se4")
    short = straight(4)
    for call in (
        lambda: ate(short, ref),
        lambda: rpe(short, ref, 1.0),
        lambda: kitti_drift(short, ref),
        lambda: endpoint_error(short, ref),
        lambda: frame_errors(short, ref),
        lambda: frame_errors(planar_increments(short), planar_increments(ref)),
    ):
        with pytest.raises(DataError, match="4 .* 5"):
            call()


# --- endpoint -------------------------------------------------------------------------------
def test_square_endpoint_error():
    ref = square(side=10.0)  # 40 m, ends where it started
    positions = ref.positions.copy()
    positions[-1] += [1.2, -1.6, 0.0]  # 2 m off at the end
    est = Trajectory(ref.stamps, positions, ref.quaternions)
    result = endpoint_error(est, ref)
    assert result["metres"] == pytest.approx(2.0)
    assert result["percent_of_path"] == pytest.approx(5.0)
    assert end_to_start_gap(ref) == pytest.approx(0.0)
    assert end_to_start_gap(est) == pytest.approx(2.0)


# --- RPE ------------------------------------------------------------------------------------
def test_rpe_of_steps_ten_percent_too_long():
    # 11 frames 1 m apart; the estimate steps 1.1 m. Over 2 m each pair (i, i+2) is 0.2 m
    # too long, with frames 0..8 starting a pair.
    ref, est = straight(11), straight(11, step=1.1)
    result = rpe(est, ref, delta_m=2.0)
    assert result["pairs"] == 9
    assert result["trans_rmse"] == pytest.approx(0.2) and result["trans_mean"] == pytest.approx(0.2)
    assert result["rot_rmse_deg"] == pytest.approx(0.0, abs=1e-9)


def test_rpe_of_a_heading_that_creeps():
    # Same positions, heading 0.01 rad more every frame: every 2 m pair turns 0.02 rad too
    # much, and the estimated displacement, seen from the estimated heading 0.01·i, is the
    # true 2 m rotated by -0.01·i: an error of 2·2·sin(0.01·i/2).
    ref, est = straight(11), straight(11, yaw_rate=0.01)
    result = rpe(est, ref, delta_m=2.0)
    assert result["rot_mean_deg"] == pytest.approx(math.degrees(0.02))
    expected = [4.0 * math.sin(0.005 * i) for i in range(9)]
    assert result["trans_mean"] == pytest.approx(np.mean(expected))
    assert result["trans_max"] == pytest.approx(max(expected))


def test_rpe_on_a_route_shorter_than_the_distance_has_no_pairs():
    result = rpe(straight(5), straight(5), delta_m=10.0)
    assert result["pairs"] == 0 and math.isnan(result["trans_rmse"])
    with pytest.raises(MetricsError, match="positive"):
        rpe(straight(5), straight(5), delta_m=0.0)


# --- KITTI drift ----------------------------------------------------------------------------
def test_kitti_drift_of_one_percent_too_long_steps():
    # 201 frames 1 m apart (200 m). The devkit's 100 m segment from frame i ends at the first
    # frame strictly beyond 100 m, i + 101; that segment is 101 m long and the estimate makes
    # it 1.01 m too long: 1.01 / 100 m = 1.01 %. Starts 0, 10, ..., 90 fit (10 segments);
    # no 200 m segment fits.
    ref, est = straight(201), straight(201, step=1.01)
    result = kitti_drift(est, ref)
    assert result["segments"] == 10
    assert result["trans_pct"] == pytest.approx(1.01)
    assert result["rot_deg_per_100m"] == pytest.approx(0.0, abs=1e-9)


def test_kitti_drift_of_a_creeping_heading():
    # Heading 0.001 rad more per frame: each 101-frame segment turns 0.101 rad too much,
    # 5.787 deg per 100 m; the displacement error is 2·101·sin(0.001·i/2) for start i.
    ref, est = straight(201), straight(201, yaw_rate=0.001)
    result = kitti_drift(est, ref)
    assert result["rot_deg_per_100m"] == pytest.approx(math.degrees(0.101))
    starts = range(0, 100, 10)
    assert result["trans_pct"] == pytest.approx(np.mean([2 * 101 * math.sin(0.0005 * i) for i in starts]))


def test_kitti_drift_is_none_below_100_m():
    assert kitti_drift(straight(100), straight(100)) is None  # 99 m
    assert kitti_drift(straight(102), straight(102)) is not None  # frame 101 lies beyond 100 m


# --- per-frame errors -----------------------------------------------------------------------
def test_frame_errors_by_hand():
    n = 21
    ref = (np.ones(n), np.zeros(n), np.zeros(n))
    est = (np.full(n, 1.1), np.zeros(n), np.full(n, 0.01))
    result = frame_errors(est, ref)
    assert result["frames"] == n - 1
    for key in ("mean", "median", "rmse", "max"):
        assert result[f"trans_{key}"] == pytest.approx(0.1)
        assert result[f"rot_{key}_deg"] == pytest.approx(math.degrees(0.01))
    # Trajectories dead-reckoned from the same increments give the same per-frame errors.
    from_trajectories = frame_errors(integrate_increments(*est), integrate_increments(*ref))
    assert from_trajectories["trans_mean"] == pytest.approx(0.1)
    assert from_trajectories["rot_mean_deg"] == pytest.approx(math.degrees(0.01))


def test_frame_errors_with_scale_alignment():
    rng = np.random.default_rng(5)
    n = 30
    ref = np.column_stack([rng.uniform(0.5, 1.0, n), rng.normal(0, 0.05, n), rng.normal(0, 0.05, n)])
    est = ref * [2.0, 2.0, 1.0]  # translations twice too long, rotations right
    assert frame_errors(est, ref)["trans_mean"] > 0.4
    result = frame_errors(est, ref, scale_align=True)
    assert result["scale"] == pytest.approx(0.5)
    assert result["trans_max"] == pytest.approx(0.0, abs=1e-12)
    translation, rotation, scale = frame_error_series(est, ref, scale_align=True)
    assert translation.shape == (n - 1,) and np.allclose(rotation, 0.0)


def test_frame_errors_reject_a_bad_shape():
    with pytest.raises(MetricsError, match="forward, left, yaw"):
        frame_errors(np.zeros((4, 2)), np.zeros((4, 2)))


# --- association ----------------------------------------------------------------------------
def test_associate_drops_unmatched_frames():
    ref = straight(10)
    est = ref.select(np.array([0, 2, 3, 7]))
    est = Trajectory(est.stamps + 0.004, est.positions, est.quaternions)
    est_matched, ref_matched = associate(est, ref, max_dt=0.01)
    assert np.array_equal(ref_matched.stamps, [0, 2, 3, 7])
    assert len(est_matched) == 4
    with pytest.raises(MetricsError, match="no estimated pose"):
        associate(est, ref, max_dt=0.001)


# --- cross-check with evo (the test extra; GPL, so never imported by services/) --------------
def test_agrees_with_evo():
    evo_trajectory = require("evo.core.trajectory", "test")
    evo_metrics = require("evo.core.metrics", "test")
    ref = random_3d(n=60, seed=7)
    rng = np.random.default_rng(8)
    est = apply_transform(ref, yaw_matrix(0.3), np.array([1.0, 2.0, 0.5]), scale=0.8)
    est = Trajectory(est.stamps, est.positions + rng.normal(0, 0.3, est.positions.shape), est.quaternions)

    def to_evo(traj):
        # evo orders quaternions w, x, y, z.
        return evo_trajectory.PoseTrajectory3D(traj.positions, traj.quaternions[:, [3, 0, 1, 2]], traj.stamps)

    for kind, flags in (("none", {}), ("se3", {"align": True}), ("sim3", {"align": True, "correct_scale": True})):
        evo_est, evo_ref = to_evo(est), to_evo(ref)
        if flags:
            evo_est.align(evo_ref, correct_scale=flags.get("correct_scale", False))
        metric = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        metric.process_data((evo_ref, evo_est))
        stats = metric.get_all_statistics()
        ours = ate(est, ref, align=kind)
        for key in ("rmse", "mean", "median", "max", "std"):
            assert ours[key] == pytest.approx(stats[key], rel=1e-9), (kind, key)

    for relation, key in ((evo_metrics.PoseRelation.translation_part, "trans"), (evo_metrics.PoseRelation.rotation_angle_deg, "rot")):
        metric = evo_metrics.RPE(relation, delta=1, delta_unit=evo_metrics.Unit.frames, all_pairs=True)
        metric.process_data((to_evo(ref), to_evo(est)))
        ours = frame_errors(est, ref)
        suffix = "" if key == "trans" else "_deg"
        assert ours[f"{key}_rmse{suffix}"] == pytest.approx(metric.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-6)
        assert ours[f"{key}_max{suffix}"] == pytest.approx(metric.get_statistic(evo_metrics.StatisticsType.max), rel=1e-6)
