"""Trajectory type, TUM/KITTI files, camera/planar conventions and increments."""

import math

import numpy as np
import pytest

from services.common.errors import DataError
from services.evaluation.trajectory import (
    Trajectory,
    TrajectoryFormatError,
    camera_to_planar,
    integrate_increments,
    planar_increments,
    planar_to_camera,
    read_kitti,
    read_tum,
    write_kitti,
    write_tum,
)


def random_trajectory(n=20, seed=0) -> Trajectory:
    rng = np.random.default_rng(seed)
    quaternions = rng.normal(size=(n, 4))
    return Trajectory(np.arange(n) * 0.1 + 1e9 / 3, rng.normal(size=(n, 3)) * 100, quaternions)


def test_from_planar_round_trips_through_matrices_and_planar():
    yaw = np.array([0.0, math.pi / 2, -3.0, 3.0])
    traj = Trajectory.from_planar([0, 1, 2, 3], [0.0, 1.0, 2.0, 3.0], [0.0, -1.0, 5.0, 2.0], yaw)
    # A yaw of +90 deg turns the body's x axis onto the world's y axis (counter-clockwise).
    assert np.allclose(traj.matrices()[1][:3, 0], [0.0, 1.0, 0.0])
    again = Trajectory.from_matrices(traj.stamps, traj.matrices())
    x, y, back = again.planar()
    assert np.allclose(x, [0, 1, 2, 3]) and np.allclose(y, [0, -1, 5, 2])
    assert np.allclose(back, yaw)


def test_path_length_of_a_unit_square():
    traj = Trajectory.from_planar(range(5), [0, 1, 1, 0, 0], [0, 0, 1, 1, 0], np.zeros(5))
    assert traj.path_length() == pytest.approx(4.0)
    assert np.allclose(traj.cumulative_distances(), [0, 1, 2, 3, 4])
    assert len(traj) == 5


def test_constructor_rejects_bad_shapes_and_non_finite_values():
    with pytest.raises(TrajectoryFormatError, match="positions"):
        Trajectory(np.zeros(3), np.zeros((2, 3)), np.tile([0, 0, 0, 1.0], (3, 1)))
    with pytest.raises(TrajectoryFormatError, match="pose 1"):
        Trajectory(np.zeros(2), [[0, 0, 0], [0, np.nan, 0]], np.tile([0, 0, 0, 1.0], (2, 1)))
    with pytest.raises(TrajectoryFormatError, match="zero length"):
        Trajectory(np.zeros(1), np.zeros((1, 3)), np.zeros((1, 4)))
    assert issubclass(TrajectoryFormatError, DataError)


def test_tum_round_trip_is_exact(tmp_path):
    traj = random_trajectory()
    path = write_tum(tmp_path / "sub" / "a.tum", traj)
    back = read_tum(path)
    assert np.array_equal(back.stamps, traj.stamps)
    assert np.array_equal(back.positions, traj.positions)
    assert np.allclose(back.quaternions, traj.quaternions, atol=1e-15)


def test_kitti_round_trip_keeps_poses(tmp_path):
    traj = random_trajectory(seed=1)
    back = read_kitti(write_kitti(tmp_path / "a.txt", traj), stamps=traj.stamps)
    assert np.array_equal(back.positions, traj.positions)
    assert np.allclose(back.matrices(), traj.matrices(), atol=1e-13)
    assert np.array_equal(read_kitti(tmp_path / "a.txt").stamps, np.arange(len(traj)))


def test_tum_reader_skips_comments_and_blank_lines(tmp_path):
    path = tmp_path / "c.tum"
    path.write_text("# header\n\n1.0 1 2 3 0 0 0 1  # trailing comment\n2.0 4 5 6 0 0 0 2\n")
    traj = read_tum(path)
    assert np.allclose(traj.positions, [[1, 2, 3], [4, 5, 6]])
    assert np.allclose(traj.quaternions[1], [0, 0, 0, 1])


@pytest.mark.parametrize(
    "content, message",
    [
        ("1 2 3 4 5 6 7 1\n1 2 3 4 5 6 7\n", r"line 2: expected 8 numbers"),
        ("1 2 3 4 5 6 7 1\n2 2 x 4 5 6 7 1\n", r"line 2: column 'ty' is not a number"),
        ("# c\n1 2 3 nan 0 0 0 1\n", r"line 2: column 'tz' is not finite"),
        ("1 2 3 4 0 0 0 0\n", r"line 1: quaternion has zero length"),
        ("# only a comment\n\n", r"no poses"),
    ],
)
def test_tum_reader_names_file_and_line(tmp_path, content, message):
    path = tmp_path / "bad.tum"
    path.write_text(content)
    with pytest.raises(TrajectoryFormatError, match=message) as error:
        read_tum(path)
    assert str(path) in str(error.value)


@pytest.mark.parametrize(
    "content, message",
    [
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", r"line 2: expected 12 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 inf\n", r"line 1: column 'tz' is not finite"),
        ("2 0 0 0 0 1 0 0 0 0 1 0\n", r"line 1: .*not a rotation"),
        ("", r"no poses"),
    ],
)
def test_kitti_reader_names_file_and_line(tmp_path, content, message):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(TrajectoryFormatError, match=message) as error:
        read_kitti(path)
    assert str(path) in str(error.value)


def test_missing_file_and_wrong_stamp_count(tmp_path):
    with pytest.raises(TrajectoryFormatError, match="no such file"):
        read_tum(tmp_path / "absent.tum")
    path = tmp_path / "k.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(TrajectoryFormatError, match="1 poses but 2 stamps"):
        read_kitti(path, stamps=[0.0, 1.0])


def test_camera_to_planar_maps_forward_right_and_turns():
    # Camera moves 2 m forward (+z), then 1 m right (+x), and finally turns left: a
    # rotation about camera -y (up) by +30 deg, which is yaw +30 deg in the planar world.
    turn = np.deg2rad(30.0)
    up_rotation = np.array(  # rotation about camera y by -30 deg
        [[math.cos(-turn), 0, math.sin(-turn)], [0, 1, 0], [-math.sin(-turn), 0, math.cos(-turn)]]
    )
    matrices = np.tile(np.eye(4), (3, 1, 1))
    matrices[1, :3, 3] = [0.0, 0.0, 2.0]
    matrices[2, :3, 3] = [1.0, 0.0, 2.0]
    matrices[2, :3, :3] = up_rotation
    planar = camera_to_planar(Trajectory.from_matrices([0, 1, 2], matrices))
    x, y, yaw = planar.planar()
    assert np.allclose(x, [0, 2, 2]) and np.allclose(y, [0, 0, -1])
    assert np.allclose(yaw, [0, 0, turn])
    assert np.allclose(planar.positions[:, 2], 0.0)


def test_camera_to_planar_keep_height_inverts(shared_data):
    traj = read_kitti(shared_data / "kitti06_clip" / "poses.txt")
    planar_full = camera_to_planar(traj, keep_height=True)
    assert np.allclose(planar_to_camera(planar_full).matrices(), traj.matrices(), atol=1e-12)
    # The clip drives nearly straight along camera z: in the planar world that is +x.
    x, y, yaw = camera_to_planar(traj).planar()
    assert x[-1] == pytest.approx(traj.positions[-1, 2])
    assert y[-1] == pytest.approx(-traj.positions[-1, 0])
    assert abs(y[-1]) < 0.05 * x[-1]
    assert traj.path_length() == pytest.approx(59.86, abs=0.01)  # the data README says 59.9 m


def test_increments_round_trip_and_known_values():
    # Forward 1 m, turn left 90 deg, forward 1 m: ends at (1, 1) facing +y.
    traj = integrate_increments([0, 1, 0, 1], [0, 0, 0, 0], [0, 0, math.pi / 2, 0])
    x, y, yaw = traj.planar()
    assert np.allclose(x, [0, 1, 1, 1]) and np.allclose(y, [0, 0, 0, 1])
    assert np.allclose(yaw[-1], math.pi / 2)
    assert np.array_equal(traj.stamps, [0, 1, 2, 3])

    rng = np.random.default_rng(3)
    n = 50
    forward, left, yaw = rng.uniform(0, 1, n), rng.normal(0, 0.1, n), rng.normal(0, 0.5, n)
    forward[0] = left[0] = yaw[0] = 0.0
    walked = integrate_increments(forward, left, yaw, np.arange(n) * 0.5, x0=3.0, y0=-2.0, heading0=2.5)
    assert walked.planar()[0][0] == 3.0 and walked.planar()[1][0] == -2.0
    back = planar_increments(walked)
    assert np.allclose(back[0], forward) and np.allclose(back[1], left) and np.allclose(back[2], yaw)


def test_integrate_increments_rejects_mismatched_lengths():
    with pytest.raises(DataError, match="differ in length"):
        integrate_increments([1, 2], [0], [0, 0])


def test_quaternion_and_matrix_conversions_agree_with_scipy():
    """numpy's conversions (the container image has no scipy.spatial) against scipy's Rotation,
    on random rotations and half turns about each axis (where the trace is smallest)."""
    from scipy.spatial.transform import Rotation

    half_turns = Rotation.from_rotvec(np.pi * np.eye(3))
    rotations = Rotation.concatenate([Rotation.random(500, random_state=4), half_turns, Rotation.identity(1)])
    matrices = np.zeros((len(rotations), 4, 4))
    matrices[:, :3, :3] = rotations.as_matrix()
    matrices[:, 3, 3] = 1.0
    traj = Trajectory.from_matrices(np.arange(len(rotations)), matrices)
    ours = traj.quaternions
    theirs = rotations.as_quat()
    sign = np.sign(np.sum(ours * theirs, axis=1))   # q and -q are the same rotation
    assert np.allclose(ours, sign[:, None] * theirs, atol=1e-12)
    assert np.allclose(traj.rotations(), Rotation.from_quat(ours).as_matrix(), atol=1e-12)
    # A matrix rounded as in a text file still gives a unit quaternion of a rotation next to it.
    rounded = Trajectory.from_matrices(traj.stamps, np.round(matrices, 4))
    assert np.allclose(np.linalg.norm(rounded.quaternions, axis=1), 1.0)
    assert np.allclose(rounded.rotations(), traj.rotations(), atol=1e-3)
