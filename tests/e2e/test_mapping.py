"""The demo as README.md shows it, in a real run: `gridslam demo` runs the whole stack as
processes on two laps of the synthetic corridor world (stereo ego-motion, the grid-cell network,
metric closures measured from the images, the gtsam pose graph); the closures it confirms join
lap 2 to lap 1, the map keeps them, and every figure README.md states is the golden one
(tests/golden/demo.json: counts equal, accuracy within 2 %)."""

import csv
import json
import math
import subprocess
import sys

from services.evaluation.trajectory import read_tum
from tests import golden
from tests.netutil import REPO, endpoint, free_port

GRIDSLAM = [sys.executable, "-m", "services.cli"]
LAP = 374   # frames of one lap of the demo's world (748 over its two laps)


def test_the_demo_joins_lap_2_to_lap_1_and_gives_the_golden_figures(tmp_path):
    out = tmp_path / "demo"
    done = subprocess.run(GRIDSLAM + ["demo", "--listen", endpoint(free_port()), "--out", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    rows = list(csv.DictReader(open(out / "loop_closures.csv")))
    accepted = [r for r in rows if r["accepted"] == "true"]
    assert all(r["measurement"] == "stereo" for r in accepted)
    truth = read_tum(out / "groundtruth.tum").positions
    for r in accepted:   # lap 2 onto the same place of lap 1
        frame, matched = int(r["frame"]), int(r["matched_frame"])
        assert frame >= LAP and matched < LAP and abs((frame - matched) - LAP) <= 15
        assert math.dist(truth[frame, :2], truth[matched, :2]) < 0.5
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["summary"]["map_closures"]["accepted"] == len(accepted)
    stages = metrics["stages"]
    assert stages["map"]["frames"] == 2 * LAP and "latency_ms" not in stages["map"]
    golden.check("demo", out)
    # The table the demo prints is the one `gridslam export table` prints from its folder.
    table = subprocess.run(GRIDSLAM + ["export", "table", str(out)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert table.returncode == 0 and table.stdout.strip() in done.stdout, table.stderr
    assert "map: latency" not in table.stdout and "map_online: latency p50 from frame" in table.stdout
