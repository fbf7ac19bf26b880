"""`gridslam run --fleet --view --foxglove` from the real command line (docs/fleet.md): two robots
on the corridor world, one viewer and one Foxglove server for the fleet, both fed by the real
fleet map and still serving once the fleet has finished. The viewer's state is read back over
HTTP, the Foxglove server's topics by the npm `@foxglove/ws-protocol` client, and both are
checked against the fleet's ground truth and what the run recorded."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import threading
import urllib.request
from base64 import b64decode

import pytest

from services.evaluation.trajectory import read_tum
from tests.browser import Browser, chromium_and_driver
from tests.extras import require
from tests.netutil import REPO, endpoint, free_port, start, wait_for

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def fleet_run(tmp_path_factory):
    require("foxglove", "foxglove")
    out = tmp_path_factory.mktemp("fleet") / "results"
    ports = {"viewer": free_port(), "foxglove": free_port(), "router": free_port()}
    process = start(["run", "--fleet", "--source", "synthetic:0", "--preset", "synthetic", "--egomotion", "passthrough",
                     "--n-frames", "160", "--robot-start", "0", "--robot-start", "80", "--listen",
                     endpoint(ports["router"]), "--out", str(out), "--view", f"127.0.0.1:{ports['viewer']}",
                     "--foxglove", str(ports["foxglove"])])
    stdout: list[str] = []
    stderr: list[str] = []
    for stream, lines in ((process.stdout, stdout), (process.stderr, stderr)):
        threading.Thread(target=lambda s=stream, kept=lines: kept.extend(s), daemon=True).start()
    try:
        wait_for(lambda: any("serving it until Ctrl-C" in line for line in stdout) or process.poll() is not None,
                 timeout=400, period=0.5)
        assert process.poll() is None, "".join(stdout)[-2000:] + "".join(stderr)[-3000:]
        yield {"out": out, "ports": ports, "process": process, "stdout": stdout}
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()


def truth_end(out, robot: str) -> tuple[float, float]:
    truth = read_tum(out / "fleet" / f"{robot}.groundtruth.tum")
    return float(truth.positions[-1][0]), float(truth.positions[-1][1])


def test_the_fleet_run_starts_one_viewer_and_one_foxglove_server_and_says_where(fleet_run):
    ports, stdout = fleet_run["ports"], fleet_run["stdout"]
    viewer, foxglove = f"http://127.0.0.1:{ports['viewer']}/", f"ws://127.0.0.1:{ports['foxglove']}"
    assert f"viewer: {viewer}\n" in stdout and f"foxglove: {foxglove}\n" in stdout
    assert stdout[-1] == f"the fleet has finished; serving it until Ctrl-C: viewer {viewer}, foxglove {foxglove}\n"
    logs = fleet_run["out"] / "fleet" / "logs"
    assert (logs / "viewer.log").exists() and (logs / "foxglove.log").exists()
    for robot in ("a", "b"):   # not one per robot
        assert not list((fleet_run["out"] / robot).glob("logs/viewer*.log"))


def test_the_viewer_draws_both_robots_in_the_fleet_frame(fleet_run):
    out, port = fleet_run["out"], fleet_run["ports"]["viewer"]
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/state.json", timeout=10) as response:
        state = json.loads(response.read())
    metrics = json.loads((out / "metrics.json").read_text())["fleet"]
    fleet = state["fleet"]
    assert state["robot"] == "a" and set(fleet["robots"]) == {"a", "b"}
    assert metrics["joined_at"]["b"] is not None
    for robot in ("a", "b"):
        row = fleet["robots"][robot]
        assert row["joined"] and row["part"] == "a", row
        # Its last pose in the fleet frame is where the robot truly ended (truth in robot a's frame).
        assert math.dist(row["track"]["pose"][:2], truth_end(out, robot)) < 0.3, (robot, row["track"]["pose"])
        assert len(fleet["map"]["experiences"][robot]) == row["experiences"] > 0
    assert fleet["robots"]["b"]["joined_at"] == metrics["joined_at"]["b"]
    # Each track holds the robot's fleet poses from its join on (those the run's recorder heard
    # once joined; robot a's from its first frame the fleet map placed).
    for robot in ("a", "b"):
        joined_poses = metrics["online_error_after_join_m"][robot]["frames"]
        assert joined_poses > 20 and abs(len(fleet["robots"][robot]["track"]["points"]) - joined_poses) <= 2, robot
    assert fleet["closures"]["accepted"] == metrics["inter_robot_closures_accepted"] > 0
    assert fleet["snapshots"] >= 1   # asked at start (and when the fleet map came up)


def test_foxglove_publishes_each_joined_robots_pose_and_path_in_the_map_frame(fleet_run):
    from services.ros2wire.messages import RosMessages
    from tests import npm_foxglove

    out = fleet_run["out"]
    received = npm_foxglove.receive(f"ws://127.0.0.1:{fleet_run['ports']['foxglove']}")
    assert received["errors"] == [], received["errors"]
    schemas = {channel["topic"]: channel["schemaName"] for channel in received["channels"]}
    ros = RosMessages()
    metrics = json.loads((out / "metrics.json").read_text())["fleet"]
    for robot in ("a", "b"):
        assert schemas[f"/fleet/{robot}/pose"] == "geometry_msgs/msg/PoseWithCovarianceStamped"
        assert schemas[f"/fleet/{robot}/path"] == "nav_msgs/msg/Path"
        poses = [ros.store.deserialize_cdr(b64decode(data), "geometry_msgs/msg/PoseWithCovarianceStamped")
                 for _, data in received["messages"][f"/fleet/{robot}/pose"]]
        assert {pose.header.frame_id for pose in poses} == {"map"}
        last = poses[-1].pose.pose.position
        assert math.dist((last.x, last.y), truth_end(out, robot)) < 0.3
        path = ros.store.deserialize_cdr(b64decode(received["messages"][f"/fleet/{robot}/path"][-1][1]), "nav_msgs/msg/Path")
        assert path.header.frame_id == "map" and len(path.poses) == len(poses)   # every pose since it joined
        end = path.poses[-1].pose.position
        assert (end.x, end.y) == (last.x, last.y)
    assert abs(len(received["messages"]["/fleet/b/pose"]) - metrics["online_error_after_join_m"]["b"]["frames"]) <= 2


# What the page draws of the fleet (services/viewer/static/viewer.js, drawFleet).
FLEET_PAGE = """
const box = (element) => { const b = element.getBBox(); return [Math.round(b.width), Math.round(b.height)]; };
const tracks = [...document.querySelectorAll('#fleet-tracks path')];
return {
  hidden: document.getElementById('fleet-panel').hidden,
  tracks: Object.fromEntries(tracks.map((p) => [p.dataset.robot, [Number(p.dataset.count), box(p), p.style.stroke]])),
  poses: [...document.querySelectorAll('#fleet-poses polygon')].map((p) => p.dataset.robot),
  closures: Number(document.getElementById('fleet-closures').dataset.count),
  legend: [...document.querySelectorAll('#fleet-legend li')].map((li) => li.textContent),
};
"""
SCREENSHOT = REPO / "docs" / "img" / "viewer-fleet.png"


def test_a_browser_draws_both_robots_in_the_fleet_frame_each_in_its_colour(fleet_run, tmp_path):
    chromium, chromedriver = chromium_and_driver()
    browser = Browser(chromium, chromedriver, tmp_path / "profile")
    try:
        browser.open(f"http://127.0.0.1:{fleet_run['ports']['viewer']}/")
        page = wait_for(lambda: (p := browser.script(FLEET_PAGE)) and len(p["tracks"]) == 2 and p, timeout=20, period=0.3)
        assert not page["hidden"] and sorted(page["poses"]) == ["a", "b"]
        (count_a, box_a, colour_a), (count_b, _, colour_b) = page["tracks"]["a"], page["tracks"]["b"]
        assert count_a > 100 and count_b > 20 and colour_a != colour_b
        assert box_a[0] > 200 and box_a[1] > 100   # robot a's lap of the corridor, on screen, not a dot
        assert page["closures"] > 0   # the accepted inter-robot closures between the two robots
        assert page["legend"][0].startswith("robot a · fleet frame") and "robot b · joined at frame" in page["legend"][1]
        target = SCREENSHOT if os.environ.get("GRIDSLAM_UPDATE_SCREENSHOT") == "1" else tmp_path / "viewer-fleet.png"
        target.write_bytes(browser.screenshot())
    finally:
        browser.close()


def test_ctrl_c_ends_the_served_fleet(fleet_run):
    process = fleet_run["process"]
    process.send_signal(signal.SIGINT)
    assert process.wait(timeout=60) == 0
