"""The map beats the odometry, in a real run (issue 11): the whole stack as processes on two laps
of a small synthetic world (stereo ego-motion, the grid-cell network, metric closures measured
from the images, the gtsam pose graph); the closures it confirms join lap 2 to lap 1, the map
keeps them, and the map's error is below the odometry's."""

import csv
import json
import math
import subprocess
import sys

import numpy as np

from services.evaluation.trajectory import read_tum
from tests.netutil import REPO, endpoint, free_port

GRIDSLAM = [sys.executable, "-m", "services.cli"]
# A 6 m × 4 m corridor loop: 174 frames a lap at 0.1 m per frame.
SMALL_WORLD = ["--world", "length=6", "--world", "breadth=4", "--laps", "2"]
LAP = 174


def test_a_run_confirms_closures_of_lap_2_to_lap_1_and_the_map_beats_the_odometry(tmp_path):
    out = tmp_path / "run"
    done = subprocess.run(GRIDSLAM + ["run", "--source", "synthetic:3", "--preset", "synthetic", "--egomotion", "stereo",
                                      *SMALL_WORLD, "--listen", endpoint(free_port()), "--out", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    rows = list(csv.DictReader(open(out / "loop_closures.csv")))
    accepted = [r for r in rows if r["accepted"] == "true"]
    assert len(accepted) >= 20, f"{len(accepted)} closures accepted of {len(rows)}"
    assert all(r["measurement"] == "stereo" for r in accepted)
    truth = read_tum(out / "groundtruth.tum").positions
    for r in accepted:   # lap 2 onto the same place of lap 1
        frame, matched = int(r["frame"]), int(r["matched_frame"])
        assert frame >= LAP and matched < LAP and abs((frame - matched) - LAP) <= 15
        assert math.dist(truth[frame, :2], truth[matched, :2]) < 0.5
    metrics = json.loads((out / "metrics.json").read_text())
    closures = metrics["summary"]["map_closures"]
    assert closures["accepted"] == len(accepted) and closures["accepted_false"] == 0
    stages = metrics["stages"]
    assert stages["map"]["ate_se2"]["rmse"] < 0.8 * stages["gridcells"]["ate_se2"]["rmse"]
    assert stages["map"]["frames"] == 2 * LAP and np.isfinite(stages["map_online"]["ate_se2"]["rmse"])
