"""gridslam as a node of a ROS 2 graph, end to end: `gridslam run --ros2` on the real NuBot
stereo frames around a `gridslam router`, heard by an independent rmw_zenoh client
(zenoh-ros2-sdk, tests/ros2client.py) that discovers the node and its topics through
liveliness and receives /gridslam/odom and /tf for every frame, equal to the run's files."""

from __future__ import annotations

import math
import subprocess
import time

import numpy as np
import pytest

from services.evaluation.trajectory import read_tum
from tests.netutil import GRIDSLAM, REPO, endpoint, free_port, port_open, start, wait_for
from tests.ros2client import Client

pytestmark = pytest.mark.e2e

NUBOT_FRAMES = 205
TOPICS = {"/gridslam/odom": "nav_msgs/msg/Odometry", "/tf": "tf2_msgs/msg/TFMessage",
          "/gridslam/pose": "geometry_msgs/msg/PoseWithCovarianceStamped", "/gridslam/path": "nav_msgs/msg/Path",
          "/gridslam/experience_map": "visualization_msgs/msg/MarkerArray",
          "/gridslam/grid_activity": "sensor_msgs/msg/Image"}


def stamp_s(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def yaw(q) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


@pytest.fixture
def router():
    port = free_port()
    process = start(["router", "--listen", endpoint(port)])
    try:
        wait_for(lambda: port_open(port), timeout=15)
        yield port
    finally:
        process.terminate()
        process.communicate(timeout=10)


def test_nubot_run_is_a_ros2_node_heard_by_an_outside_rmw_zenoh_client(router, shared_data, tmp_path):
    client = Client(router, tmp_path / "msgs")
    try:
        for topic, msgtype in TOPICS.items():
            if topic != "/gridslam/grid_activity":
                client.subscribe(topic, msgtype)
        out = tmp_path / "run"
        run = subprocess.Popen(GRIDSLAM + ["run", "--source", f"stereo:{shared_data / 'nubot_scene1'}", "--preset", "nubot",
                                           "--ros2", "--connect", endpoint(router), "--out", str(out), "--no-mcap"],
                               cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        # The graph during the run, as `ros2 node list` and `ros2 topic list -t` would show it.
        nodes, topics = set(), {}
        deadline = time.monotonic() + 600
        while run.poll() is None and time.monotonic() < deadline:
            nodes |= client.nodes()
            topics.update(client.topics())
            if ("/gridslam", "gridslam") in nodes and all(t in topics for t in TOPICS):
                break
            time.sleep(0.5)
        stdout, stderr = run.communicate(timeout=600)
        assert run.returncode == 0, stderr[-3000:]
        time.sleep(1.0)   # the last samples on their way
    finally:
        client.close()
    assert ("/gridslam", "gridslam") in nodes, nodes
    assert {topic: topics.get(topic) for topic in TOPICS} == {topic: [msgtype] for topic, msgtype in TOPICS.items()}

    odometry = client.received["/gridslam/odom"]
    grid = read_tum(out / "gridcells.tum")
    online = read_tum(out / "map_online.tum")
    print(f"/gridslam/odom: {len(odometry)} of {NUBOT_FRAMES} messages")
    assert len(odometry) == NUBOT_FRAMES == len(grid)
    assert all((m.header.frame_id, m.child_frame_id) == ("odom", "base_link") for m in odometry)
    stamps = np.array([stamp_s(m.header) for m in odometry])
    positions = np.array([(m.pose.pose.position.x, m.pose.pose.position.y) for m in odometry])
    assert np.allclose(stamps, grid.stamps, atol=1e-6, rtol=0)
    odom_error = np.abs(positions - grid.positions[:, :2]).max()
    assert odom_error <= 1e-6
    # The covariance grows along the path (the increments' covariances propagated).
    variances = np.array([m.pose.covariance[0] + m.pose.covariance[7] for m in odometry])
    assert variances[-1] > variances[1] > 0

    # /tf: odom → base_link every frame, map → odom from every map pose; composed, the map pose.
    transforms: dict[tuple[str, str], dict[float, tuple]] = {}
    for message in client.received["/tf"]:
        for t in message.transforms:
            transforms.setdefault((t.header.frame_id, t.child_frame_id), {})[round(stamp_s(t.header), 6)] = \
                (t.transform.translation.x, t.transform.translation.y, yaw(t.transform.rotation))
    base, correction = transforms[("odom", "base_link")], transforms[("map", "odom")]
    assert len(base) == NUBOT_FRAMES and len(correction) == len(online) == NUBOT_FRAMES
    composed = []
    for stamp in sorted(correction):
        (cx, cy, ch), (bx, by, _) = correction[stamp], base[stamp]
        composed.append((cx + math.cos(ch) * bx - math.sin(ch) * by, cy + math.sin(ch) * bx + math.cos(ch) * by))
    map_error = np.abs(np.array(composed) - online.positions[:, :2]).max()
    poses = client.received["/gridslam/pose"]
    pose_error = np.abs(np.array([(m.pose.pose.position.x, m.pose.pose.position.y) for m in poses])
                        - online.positions[:, :2]).max()
    assert map_error <= 1e-6 and pose_error <= 1e-6 and all(m.header.frame_id == "map" for m in poses)

    # The last Path: every frame on the map as the node last had it. The run's map.tum is the
    # map's final estimate after the run, of which expmap publishes the moves larger than 1 mm or
    # 0.1 mrad (graph.MOVED): the path stays within a few of those (4.9 mm seen here).
    final = read_tum(out / "map.tum")
    path = client.received["/gridslam/path"][-1]
    assert len(path.poses) == NUBOT_FRAMES
    path_error = np.abs(np.array([(p.pose.position.x, p.pose.position.y) for p in path.poses])
                        - final.positions[:, :2]).max()
    markers = client.received["/gridslam/experience_map"]
    assert markers and markers[-1].markers[0].ns == "experiences"
    print(f"largest differences: odom/gridcells.tum {odom_error:.2e} m, tf map∘odom/map_online.tum {map_error:.2e} m, "
          f"pose/map_online.tum {pose_error:.2e} m, last path/map.tum {path_error:.2e} m; "
          f"{len(client.received['/tf'])} /tf messages, {len(client.received['/gridslam/path'])} paths, "
          f"{len(markers)} experience maps")
    assert path_error <= 0.01
