"""`gridslam odometry` as a user runs it: a few NuBot frames end to end, and bad inputs."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from services.evaluation.trajectory import read_kitti, read_tum

pytestmark = pytest.mark.e2e
REPO = Path(__file__).resolve().parents[2]


def gridslam(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "services.cli", *args]
    return subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)})


def test_nubot_stereo_as_documented(shared_data, tmp_path):
    """The command of the issue, relative path from the repository root, on 8 frames."""
    if Path(os.path.relpath(shared_data, REPO)) != Path("../shared/data"):
        pytest.skip("the shared data is not at ../shared/data from the repository root")
    out = tmp_path / "run"
    done = gridslam(
        "odometry", "--source", "stereo:../shared/data/nubot_scene1", "--preset", "nubot", "--estimator", "stereo",
        "--n-frames", "8", "--start", "40", "--reference", "../shared/data/nubot_scene1/libviso2_egomotion.csv", "--out", str(out),
    )
    assert done.returncode == 0, done.stderr
    assert "| Metric" in done.stdout and "path length" in done.stdout
    estimate = read_tum(out / "egomotion.tum")
    assert len(estimate) == 8 and len(read_kitti(out / "egomotion.kitti.txt")) == 8
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 8 and metrics["first_seq"] == 40
    # About 0.25 m per frame on this stretch, like LIBVISO2's.
    assert metrics["path_length_m"] == pytest.approx(metrics["reference"]["path_length_m"], rel=0.05)
    assert (out / "trajectory.png").stat().st_size > 1000


def test_kitti_clip_mono_writes_ground_truth(shared_data, tmp_path):
    out = tmp_path / "kitti"
    done = gridslam("odometry", "--source", f"kitti:{shared_data / 'kitti06_clip'}", "--preset", "kitti", "--estimator", "scanline",
                    "--n-frames", "5", "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert len(read_tum(out / "groundtruth.tum")) == 5
    assert json.loads((out / "metrics.json").read_text())["ground_truth"]["frame_errors"]["frames"] == 4


@pytest.mark.parametrize(
    "args,message",
    [
        (["--estimator", "orb"], "unknown estimator 'orb'"),
        (["--estimator", "stereo", "--source", "images:{left}"], "stereo calibration"),
        (["--estimator", "scanline", "--source", "stereo:{missing}"], "missing"),
        (["--estimator", "scanline", "--config", "{missing}.toml"], "config file not found"),
    ],
)
def test_bad_inputs_give_one_line_and_exit_1(shared_data, tmp_path, args, message):
    left = tmp_path / "left"
    left.mkdir()
    for k in range(3):
        shutil.copy(shared_data / "nubot_scene1" / "left" / f"{k:06d}.png", left / f"{k:06d}.png")
    values = {"left": str(left), "missing": str(tmp_path / "missing")}
    args = [arg.format(**values) for arg in args]
    if "--source" not in args:
        args += ["--source", f"images:{left}"]
    done = gridslam("odometry", *args, "--out", str(tmp_path / "out"))
    assert done.returncode == 1, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], done.stderr
