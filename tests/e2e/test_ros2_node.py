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
    # 0.1 mrad (links.MOVED): the path stays within a few of those (5.1 mm seen here).
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


def test_kitti_clip_published_as_ros2_images_gives_the_folders_mono_odometry(router, shared_data, tmp_path):
    """The client publishes the KITTI clip as sensor_msgs/Image + CameraInfo, one image after
    the pipeline has handled the previous one (a live source keeps only the newest: paced, none
    is dropped), and `--source ros2:` gives the mono odometry of the clip's folder."""
    from schemas import GridPose
    from services.common import codec, topics
    from services.source import open_source
    from tests.netutil import client_session

    clip = shared_data / "kitti06_clip"
    frames = open_source(f"kitti:{clip}", mono=True)
    reference = tmp_path / "folder"
    done = subprocess.run(GRIDSLAM + ["run", "--source", f"kitti:{clip}", "--egomotion", "mono", "--no-mapping",
                                      "--no-mcap", "--out", str(reference)], cwd=REPO, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]

    client = Client(router, tmp_path / "msgs")
    session = client_session(router)
    handled = []
    subscriber = session.declare_subscriber(topics.key("robot0", "grid/pose"),
                                            lambda s: handled.append(codec.decode(s.payload.to_bytes(), GridPose).header.seq))
    out = tmp_path / "ros2"
    run = subprocess.Popen(GRIDSLAM + ["run", "--source", "ros2:/kitti/image", "--camera-info-topic", "/kitti/camera_info",
                                       "--egomotion", "mono", "--no-mapping", "--no-mcap", "--n-frames", str(len(frames)),
                                       "--connect", endpoint(router), "--out", str(out)],
                           cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        images = client.publisher("/kitti/image", "sensor_msgs/msg/Image")
        info = client.publisher("/kitti/camera_info", "sensor_msgs/msg/CameraInfo")
        T = images.session_mgr.store.types
        # The source's subscriptions in the graph first, the image's and the CameraInfo's: what is
        # published before them is not heard (an image before its CameraInfo is given up).
        def subscribed() -> bool:
            keys = [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/*/*/*/MS/**", timeout=1.0)
                    if r.ok is not None]
            return all(any(topic in key for key in keys) for topic in ("%kitti%image", "%kitti%camera_info"))

        wait_for(subscribed, timeout=120)
        camera = frames.camera
        for index, frame in enumerate(frames):
            sec, nanosec = divmod(int(round(frame.stamp * 1e9)), 1_000_000_000)
            header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="camera")
            height, width = frame.left.shape
            projection = np.array([camera.fx, 0, camera.cx, 0, 0, camera.fy, camera.cy, 0, 0, 0, 1, 0], dtype=float)
            info.publish(header=header, height=height, width=width, distortion_model="plumb_bob", d=np.zeros(5),
                         k=np.array([camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1], dtype=float),
                         r=np.eye(3).reshape(9), p=projection, binning_x=0, binning_y=0,
                         roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
            time.sleep(0.05)
            images.publish(header=header, height=height, width=width, encoding="mono8", is_bigendian=0, step=width,
                           data=np.ascontiguousarray(frame.left).reshape(-1))
            wait_for(lambda: index in handled, timeout=120)
        stdout, stderr = run.communicate(timeout=300)
        assert run.returncode == 0, stderr[-3000:]
    finally:
        if run.poll() is None:
            run.kill()
        subscriber.undeclare()
        session.close()
        client.close()
    live, folder = read_tum(out / "egomotion.tum"), read_tum(reference / "egomotion.tum")
    assert len(live) == len(folder) == len(frames)
    error = np.abs(live.positions - folder.positions).max()
    print(f"ros2:/kitti/image against kitti:{clip.name}: {len(live)} frames, largest egomotion difference {error:.2e}")
    assert np.allclose(live.stamps, folder.stamps, atol=1e-6) and error <= 1e-9
