"""Motion-input loaders: every format (synthetic files and the real shared ones), the
conventions they follow, noise, and the one-line errors for bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.errors import DataError
from services.evaluation.trajectory import Trajectory, planar_to_camera, write_kitti, write_tum
from services.evaluation.motion_io import MotionInputError, add_noise, infer_format, load_motion


def _world_path(motion) -> np.ndarray:
    """Positions reached by the integrators' convention (turn by yaw, then move in the new
    body frame; world-frame rows simply add), starting from `motion.start`."""
    x0, y0, heading0 = motion.start
    if motion.frame == "world":
        return np.array([x0, y0]) + np.cumsum(motion.increments, axis=0)
    heading = heading0 + np.cumsum(motion.increments[:, 2])
    forward, left = motion.increments[:, 0], motion.increments[:, 1]
    dx = forward * np.cos(heading) - left * np.sin(heading)
    dy = forward * np.sin(heading) + left * np.cos(heading)
    return np.column_stack([x0 + np.cumsum(dx), y0 + np.cumsum(dy)])


def _curvy_trajectory(n=60) -> Trajectory:
    t = np.arange(n) * 0.1
    yaw = 0.3 + 0.8 * np.sin(t)
    step = 0.5 + 0.2 * np.cos(2 * t)
    x = np.cumsum(step * np.cos(yaw)) + 3.0
    y = np.cumsum(step * np.sin(yaw)) - 1.0
    return Trajectory.from_planar(t, x, y, yaw)


# --- formats ----------------------------------------------------------------------------------
def test_body_csv_with_time_column(tmp_path):
    path = tmp_path / "odometry.csv"
    path.write_text("t,forward,left,yaw\n0.0,0,0,0\n0.1,1.0,0.0,0.5\n0.2,2.0,0.5,-0.25\n")
    motion = load_motion(path)
    assert (motion.format, motion.layout, motion.frame) == ("csv", "body", "body")
    np.testing.assert_allclose(motion.stamps, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(motion.increments, [[0, 0, 0], [1.0, 0.0, 0.5], [2.0, 0.5, -0.25]])
    assert motion.groundtruth is None and motion.start == (0.0, 0.0, 0.0)


def test_world_csv_with_and_without_heading(tmp_path):
    path = tmp_path / "velocities.csv"
    path.write_text("vy,vx,heading\n0.5,1.0,0.1\n-0.5,2.0,0.2\n")
    motion = load_motion(path)
    assert motion.frame == "world"
    np.testing.assert_allclose(motion.increments, [[1.0, 0.5], [2.0, -0.5]])
    np.testing.assert_allclose(motion.heading, [0.1, 0.2])
    np.testing.assert_allclose(motion.stamps, [0, 1])  # frame index without a time column
    path.write_text("vx,vy\n1,2\n")
    assert load_motion(path).heading is None


def test_nubot_libviso2_csv_reproduces_the_authors_world_inputs(shared_data):
    """The LIBVISO2 table as body-frame increments, integrated in the network's world frame
    (turned by +90°), gives exactly the world-frame velocities and headings the authors'
    code computed (seed_reference)."""
    motion = load_motion(shared_data / "nubot_scene1" / "libviso2_egomotion.csv")
    assert (motion.layout, len(motion)) == ("libviso2", 205)
    assert motion.start == (0.0, 0.0, 0.0) and motion.network_rotation == pytest.approx(math.pi / 2)
    reference = np.genfromtxt(shared_data / "seed_reference" / "nubot_first40_frames.csv", delimiter=",", names=True)
    frames = reference["frame"].astype(int)
    heading = motion.network_rotation + np.cumsum(motion.increments[:, 2])
    forward, left = motion.increments[:, 0], motion.increments[:, 1]
    np.testing.assert_allclose((forward * np.cos(heading) - left * np.sin(heading))[frames], reference["vel_x_world_m"], atol=1e-15)
    np.testing.assert_allclose((forward * np.sin(heading) + left * np.cos(heading))[frames], reference["vel_y_world_m"], atol=1e-15)
    np.testing.assert_allclose(heading[frames] - math.pi / 2, reference["orientation_robot_rad"], atol=1e-12)
    # In the output frame the robot starts along +x (forward) and drives away from the start.
    x20, y20 = _world_path(motion)[20]
    assert x20 > 0.3 and abs(y20) < 0.1
    # README: the LIBVISO2 path is 39.4 m long.
    assert motion.step_lengths().sum() == pytest.approx(39.4, abs=0.05)


def test_kitti_poses_real_file(shared_data):
    motion = load_motion(shared_data / "kitti_poses" / "06.txt")
    assert (motion.format, motion.frame, len(motion)) == ("kitti", "body", 1101)
    times = np.loadtxt(shared_data / "kitti_poses" / "times.txt")
    np.testing.assert_allclose(motion.stamps, times)
    truth = motion.groundtruth
    assert truth.path_length() == pytest.approx(1232.6, abs=0.5)
    # The increments, integrated with the integrators' convention, rebuild the ground truth.
    np.testing.assert_allclose(_world_path(motion), truth.positions[:, :2], atol=1e-9)


def test_kitti_without_times_file_is_10_hz(shared_data):
    motion = load_motion(shared_data / "kitti06_clip" / "poses.txt")
    assert len(motion) == 51
    np.testing.assert_allclose(np.diff(motion.stamps), 0.1)
    # Nearly straight and forward: camera z became planar x.
    assert motion.increments[1:, 0].mean() > 1.0
    assert abs(motion.increments[1:, 1]).max() < 0.1


def test_kitti_and_tum_written_files_round_trip(tmp_path):
    truth = _curvy_trajectory()
    write_tum(tmp_path / "run.tum", truth)
    write_kitti(tmp_path / "run.txt", planar_to_camera(truth))
    tum = load_motion(tmp_path / "run.tum")
    kitti = load_motion(tmp_path / "run.txt")  # .txt: format from the content (12 numbers)
    assert (tum.format, kitti.format) == ("tum", "kitti")
    for motion in (tum, kitti):
        assert motion.start[:2] == pytest.approx((truth.positions[0, 0], truth.positions[0, 1]))
        np.testing.assert_allclose(_world_path(motion), truth.positions[:, :2], atol=1e-9)
    np.testing.assert_allclose(tum.stamps, truth.stamps)


def test_rat_npz_real_file(shared_data):
    motion = load_motion(shared_data / "rats" / "sargolini.npz")
    with np.load(shared_data / "rats" / "sargolini.npz") as archive:
        pos = archive["pos"]
    assert (motion.format, motion.frame, len(motion)) == ("rat", "world", len(pos))
    assert motion.start[:2] == pytest.approx(tuple(pos[0]))
    np.testing.assert_allclose(_world_path(motion), pos, atol=1e-12)
    np.testing.assert_allclose(motion.groundtruth.positions[:, :2], pos)


def test_head_keeps_the_first_rows(shared_data):
    motion = load_motion(shared_data / "kitti_poses" / "06.txt").head(40)
    assert len(motion) == 40 and len(motion.groundtruth) == 40 and motion.increments.shape == (40, 3)


def test_format_inference(tmp_path):
    (tmp_path / "a.txt").write_text("# comment\n1 0 0 0 0 0 0 1\n")
    (tmp_path / "b.dat").write_text(" ".join(["1"] * 12) + "\n")
    (tmp_path / "c.log").write_text("forward,left,yaw\n1,0,0\n")
    assert infer_format(tmp_path / "a.txt") == "tum"
    assert infer_format(tmp_path / "b.dat") == "kitti"
    assert infer_format(tmp_path / "c.log") == "csv"


# --- noise ------------------------------------------------------------------------------------
def test_noise_is_seeded_and_scaled(tmp_path):
    motion = load_motion_from_rows(tmp_path, [(0.5, 0.0, 0.01)] * 4000)
    noisy = add_noise(motion, noise_trans=0.1, noise_rot_deg=2.0, seed=3)
    again = add_noise(motion, noise_trans=0.1, noise_rot_deg=2.0, seed=3)
    other = add_noise(motion, noise_trans=0.1, noise_rot_deg=2.0, seed=4)
    np.testing.assert_array_equal(noisy.increments, again.increments)
    assert not np.array_equal(noisy.increments, other.increments)
    error = noisy.increments - motion.increments
    assert error[:, 0].std() == pytest.approx(0.05, rel=0.1)  # 10 % of a 0.5 m step
    assert np.degrees(error[:, 2].std()) == pytest.approx(2.0, rel=0.1)
    assert add_noise(motion) is motion


def load_motion_from_rows(tmp_path, rows):
    path = tmp_path / "rows.csv"
    path.write_text("forward,left,yaw\n" + "".join(f"{f},{l},{y}\n" for f, l, y in rows))
    return load_motion(path)


# --- bad input: one line naming the file, line and column ----------------------------------------
@pytest.mark.parametrize(
    "text, message",
    [
        ("forward,left,yaw\n1,0,0\n1,nan,0\n", "line 3: column 'left' is not finite: 'nan'"),
        ("forward,left,yaw\n1,0,0\n1,abc,0\n", "line 3: column 'left' is not a number: 'abc'"),
        ("forward,left\n1,0\n", "line 1: missing column 'yaw' (a body CSV needs forward,left,yaw)"),
        ("vx,speed\n1,0\n", "line 1: missing column 'vy' (a world CSV needs vx,vy)"),
        ("forward,left,yaw\n", "no data rows after the header"),
        ("forward,left,yaw\n1,0\n", "line 2: 2 fields, the header has 3"),
        ("t,forward,left,yaw\n1,0,0,0\n0.5,0,0,0\n", "line 3: column 't' goes back in time"),
        ("a,b,c\n1,2,3\n", "has none of the expected columns"),
    ],
)
def test_bad_csv(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(MotionInputError) as caught:
        load_motion(path)
    assert str(caught.value).startswith(f"{path}: ")
    assert message in str(caught.value)
    assert "\n" not in str(caught.value)
    assert isinstance(caught.value, DataError)


def test_bad_files(tmp_path):
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    cases = {
        tmp_path / "missing.csv": "no such file",
        tmp_path: "is a directory",
        empty: "file is empty",
    }
    for path, message in cases.items():
        with pytest.raises(MotionInputError, match=message):
            load_motion(path)
    odd = tmp_path / "odd.txt"
    odd.write_text("1 2 3\n")
    with pytest.raises(MotionInputError, match=r"odd.txt: cannot infer the format: the first line has 3 numbers"):
        load_motion(odd)
    with pytest.raises(MotionInputError, match=r"odd.txt: unknown format 'xyz' \(choose one of csv, kitti, tum, rat\)"):
        load_motion(odd, "xyz")
    binary = tmp_path / "blob.bin"
    binary.write_bytes(b"\xff\xfe\x00\x81" * 10)
    with pytest.raises(MotionInputError, match="blob.bin: not a text file"):
        load_motion(binary)


def test_bad_trajectory_files(tmp_path):
    tum = tmp_path / "bad.tum"
    tum.write_text("# stamp tx ty tz qx qy qz qw\n0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n")
    with pytest.raises(DataError, match=r"bad.tum: line 3: column 'tx' is not finite"):
        load_motion(tum)
    single = tmp_path / "single.tum"
    single.write_text("0 0 0 0 0 0 0 1\n")
    with pytest.raises(MotionInputError, match="needs at least 2 poses, found 1"):
        load_motion(single)


def test_bad_rat_files(tmp_path):
    path = tmp_path / "rat.npz"
    np.savez(path, t=np.arange(3.0), position=np.zeros((3, 2)))
    with pytest.raises(MotionInputError, match=r"rat.npz: missing key 'pos'"):
        load_motion(path)
    np.savez(path, t=np.arange(3.0), pos=np.array([[0, 0], [np.nan, 1], [1, 1]]))
    with pytest.raises(MotionInputError, match=r"rat.npz: key 'pos' sample 1 is not finite"):
        load_motion(path)
    np.savez(path, t=np.array([0.0, 1.0, 1.0]), pos=np.zeros((3, 2)))
    with pytest.raises(MotionInputError, match=r"key 't' sample 2 does not increase"):
        load_motion(path)
    np.savez(path, t=np.arange(3.0), pos=np.zeros(3))
    with pytest.raises(MotionInputError, match=r"'pos' has shape \(3,\), expected \(3, 2\)"):
        load_motion(path)
