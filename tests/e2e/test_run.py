"""`gridslam run` end to end: the real command line starts every service as a process around
its own router (or a shared one), and writes a results folder that evaluates the run."""

import json
import subprocess
import sys


from services.evaluation.trajectory import read_kitti, read_tum
from tests.netutil import REPO, endpoint, free_port, start_router, stop

GRIDSLAM = [sys.executable, "-m", "services.cli"]
FRAMES = 40


def run(args, timeout=240):
    return subprocess.run(GRIDSLAM + args, cwd=REPO, capture_output=True, text=True, timeout=timeout)


def test_run_writes_every_stage_and_its_evaluation(tmp_path):
    out = tmp_path / "results"
    done = run(["run", "--source", "synthetic:0", "--preset", "synthetic", "--egomotion", "passthrough", "--no-mapping",
                "--n-frames", str(FRAMES), "--listen", endpoint(free_port()), "--out", str(out)])
    assert done.returncode == 0, done.stderr
    assert "| Metric" in done.stdout and "gridcells: ATE RMSE (SE(2))" in done.stdout
    for stage in ("egomotion", "gridcells", "groundtruth"):
        assert len(read_tum(out / f"{stage}.tum")) == FRAMES
        assert len(read_kitti(out / f"{stage}.kitti.txt")) == FRAMES
    for name in ("config.json", "trajectories.png", "errors.png", "lattice.png", "logs/egomotion.log"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["summary"]["frames_sent"] == FRAMES
    egomotion, gridcells = metrics["stages"]["egomotion"], metrics["stages"]["gridcells"]
    assert egomotion["frames"] == gridcells["frames"] == FRAMES and gridcells["missing_frames"] == 0
    # Passthrough of exact odometry: dead reckoning is the ground truth; the grid cells follow it closely.
    assert egomotion["ate_se2"]["rmse"] < 1e-6
    assert gridcells["ate_se2"]["rmse"] < 0.05 * metrics["summary"]["groundtruth_path_length_m"]
    assert gridcells["latency_ms"]["p50"] > 0
    assert all(service["decode_errors"] == 0 and service["gaps"] == 0 for service in metrics["services"].values())
    assert json.loads((out / "config.json").read_text())["egomotion"] == "passthrough"


def test_frames_skipped_by_a_stride_are_no_gaps(tmp_path):
    """`--stride 3` (here in its old spelling `--step 3`, still read, with a note): seq goes up by
    3 from frame to frame, and no service counts the frames in between as missing."""
    out = tmp_path / "results"
    done = run(["run", "--source", "synthetic:0", "--preset", "synthetic", "--egomotion", "passthrough", "--step", "3",
                "--n-frames", "20", "--no-mcap", "--listen", endpoint(free_port()), "--out", str(out)])
    assert done.returncode == 0, done.stderr
    assert "--step 3 is now spelled --stride 3" in done.stderr
    assert [round(stamp * 10) for stamp in read_tum(out / "egomotion.tum").stamps][:3] == [0, 3, 6]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["stages"]["map"]["frames"] == 20
    assert {name: service["gaps"] for name, service in metrics["services"].items()} == \
           {name: 0 for name in ("source", "egomotion", "gridcells", "loopclosure", "expmap")}


def test_unknown_preset_and_missing_dataset_are_one_line_errors(tmp_path):
    for args, message in ((["--source", "synthetic:0", "--preset", "atlantis"], "atlantis"),
                          (["--source", f"kitti:{tmp_path}/absent"], "absent")):
        done = run(["run", *args, "--listen", endpoint(free_port()), "--out", str(tmp_path / "out")], timeout=60)
        assert done.returncode == 1
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("gridslam run: error:") and message in lines[0], done.stderr


def test_two_robots_share_one_router_with_separate_topics(tmp_path):
    """Scale: robots a and b run at once on one router; each result is its own world's."""
    port = free_port()
    router = start_router(port)
    try:
        runs = {robot: subprocess.Popen(
            GRIDSLAM + ["run", "--source", f"synthetic:{seed}", "--preset", "synthetic", "--egomotion", "passthrough",
                        "--integrator", "deadreckoning", "--no-mapping", "--n-frames", str(FRAMES), "--connect",
                        endpoint(port), "--robot", robot, "--out", str(tmp_path / robot)],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for robot, seed in (("a", 0), ("b", 1))}
        for robot, process in runs.items():
            out, err = process.communicate(timeout=240)
            assert process.returncode == 0, f"robot {robot}: {err}"
    finally:
        stop(router)
    for robot in ("a", "b"):
        metrics = json.loads((tmp_path / robot / "metrics.json").read_text())
        gridcells = metrics["stages"]["gridcells"]
        # Mixed topics would interleave two worlds' frames: stale drops, gaps and a wrong path.
        assert gridcells["frames"] == FRAMES and gridcells["ate_se2"]["rmse"] < 1e-3
        assert metrics["services"]["gridcells"]["stale"] == 0 and metrics["services"]["gridcells"]["gaps"] == 0
