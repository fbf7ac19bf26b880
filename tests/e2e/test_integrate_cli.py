"""`gridslam integrate` as a real subprocess: a short real input gives a results folder whose
trajectories parse with one pose per input row; bad input gives one line and exit code 1."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from services.evaluation.trajectory import read_tum

pytestmark = pytest.mark.e2e

GRIDSLAM = [sys.executable, "-m", "services.cli"]
REPO = Path(__file__).resolve().parents[2]


def gridslam(*args, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run([*GRIDSLAM, *map(str, args)], cwd=REPO, capture_output=True, text=True, timeout=timeout)


def test_integrate_nubot_first_40_frames(shared_data, tmp_path):
    out = tmp_path / "nubot"
    done = gridslam("integrate", shared_data / "nubot_scene1" / "libviso2_egomotion.csv", "--n-frames", 40, "--out", out)
    assert done.returncode == 0, done.stderr
    assert "| Metric" in done.stdout and "velocity scale" in done.stdout
    grid, deadreckoning = read_tum(out / "trajectory.tum"), read_tum(out / "deadreckoning.tum")
    assert len(grid) == len(deadreckoning) == 40
    assert not (out / "groundtruth.tum").exists()  # LIBVISO2 increments carry no truth
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["input"]["frames"] == 40 and metrics["decoder"] == "calibrated"   # the default
    assert metrics["grid"]["path_length_m"] > 0
    # The grid cells follow the dead reckoning of the same increments closely.
    assert metrics["grid"]["mean_difference_from_dr_m"] < 0.1 * metrics["deadreckoning"]["path_length_m"]
    assert (out / "trajectories.png").stat().st_size > 1000


def test_integrate_kitti_poses_with_noise_writes_ground_truth(shared_data, tmp_path):
    out = tmp_path / "kitti"
    done = gridslam("integrate", shared_data / "kitti06_clip" / "poses.txt", "--decoder", "fft", "--n-frames", 20,
                    "--noise-trans", 0.02, "--noise-rot", 0.5, "--seed", 1, "--out", out)
    assert done.returncode == 0, done.stderr
    truth = read_tum(out / "groundtruth.tum")
    assert len(truth) == len(read_tum(out / "trajectory.tum")) == 20
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["input"]["noise_trans"] == 0.02
    assert metrics["deadreckoning"]["endpoint_error_m"] > 0  # the noise moved dead reckoning off the truth
    assert "grid endpoint error" in done.stdout


def test_saturating_speed_warns_and_is_counted(tmp_path):
    """100 network units per metre at 0.1 m per frame drives the network far beyond its
    linear range: the run finishes, warns once on stderr and counts the frames."""
    motion = tmp_path / "fast.csv"
    motion.write_text("forward,left,yaw\n" + "0.1,0,0\n" * 8)
    done = gridslam("integrate", motion, "--decoder", "fft", "--velocity-scale", 100, "--out", tmp_path / "fast")
    assert done.returncode == 0, done.stderr
    assert "saturated" in done.stderr and "WARNING" in done.stderr
    metrics = json.loads((tmp_path / "fast" / "metrics.json").read_text())
    assert metrics["saturations"] == 8
    assert "| saturated frames" in done.stdout


def test_bad_input_is_one_line_and_exit_1(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("forward,left,yaw\n0.1,0,0\n0.1,NaN,0\n")
    done = gridslam("integrate", bad, "--out", tmp_path / "never")
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert lines == [f"gridslam integrate: error: {bad}: line 3: column 'left' is not finite: 'NaN'"]
    assert not (tmp_path / "never").exists()
