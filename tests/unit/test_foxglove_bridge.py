"""The Foxglove bridge's egomotion track: the increments dead-reckoned as egomotion.tum has them."""

from __future__ import annotations

import math

import pytest

from tests.extras import require

require("foxglove", "foxglove")

from schemas import EgoMotion, Header, PlanarIncrement, Time  # noqa: E402
from services.common.recovery import REPLAY_FRAMES  # noqa: E402
from services.common.runtime import RuntimeConfig  # noqa: E402
from services.evaluation.trajectory import integrate_increments  # noqa: E402
from services.ros.foxglove import FoxgloveConfig, FoxgloveService  # noqa: E402


def test_egomotion_poses_compose_the_increments_and_restart_with_a_new_run():
    service = FoxgloveService(RuntimeConfig(), FoxgloveConfig(port=0), "test")
    poses = []
    service.ros.planar_pose = lambda stage, stamp, x, y, heading: poses.append((stage, x, y, heading)) or []
    increments = [(0.0, 0.0, 0.0)] + [(0.1, 0.01, math.radians(5))] * (REPLAY_FRAMES + 10)
    try:
        for run in range(2):   # the second run starts again at seq 0: a new track from the origin
            for seq, (forward, left, yaw) in enumerate(increments):
                if run == 1 and seq == 5:   # frames sent again (a stage's kept outputs): not dead-reckoned twice
                    for again in (2, 3, 4):
                        service.on_egomotion(EgoMotion(header=Header(seq=again, stamp=Time.from_seconds(0.1 * again)),
                                                       increment=PlanarIncrement(forward=1.0, left=0.0, yaw=0.0),
                                                       quality=1.0, estimator="passthrough"))
                service.on_egomotion(EgoMotion(header=Header(seq=seq, stamp=Time.from_seconds(0.1 * seq)),
                                               increment=PlanarIncrement(forward=forward, left=left, yaw=yaw),
                                               quality=1.0, estimator="passthrough"))
    finally:
        service.teardown()
    truth = integrate_increments(*zip(*increments))
    x, y, heading = truth.planar()
    assert len(poses) == 2 * len(increments) and {stage for stage, *_ in poses} == {"egomotion"}
    for offset in (0, len(increments)):
        got = poses[offset:offset + len(increments)]
        assert [p[1] for p in got] == pytest.approx(list(x), abs=1e-9)
        assert [p[2] for p in got] == pytest.approx(list(y), abs=1e-9)
        assert [math.remainder(p[3] - h, math.tau) for p, h in zip(got, heading)] == pytest.approx([0.0] * len(got), abs=1e-9)


def test_fleet_paths_publish_joined_robots_only_in_the_map_frame_and_restart_a_split_path():
    from services.ros.foxglove import FleetPaths
    from services.ros2wire.messages import RosMessages

    ros = RosMessages()
    fleet = FleetPaths(ros, period_s=10.0, max_points=3)
    assert fleet.pose("b", 1, 5.0, 5.0, 0.0, joined=False) == []   # in its own frame: nothing
    out = fleet.pose("b", 2, 1.0, 2.0, 0.5, joined=True)
    assert [(topic, msgtype) for topic, msgtype, _, _ in out] == [("/fleet/b/pose", "geometry_msgs/msg/PoseWithCovarianceStamped")]
    pose = ros.store.deserialize_cdr(out[0][3], out[0][1])
    assert pose.header.frame_id == "map" and (pose.pose.pose.position.x, pose.pose.pose.position.y) == (1.0, 2.0)
    assert math.isclose(2 * math.atan2(pose.pose.pose.orientation.z, pose.pose.pose.orientation.w), 0.5)
    for stamp in range(3, 8):
        fleet.pose("b", stamp, float(stamp), 0.0, 0.0, joined=True)
    (topic, msgtype, stamp, data), = fleet.due(now=100.0)
    path = ros.store.deserialize_cdr(data, msgtype)
    # 6 poses thinned to every second one, the newest kept: stamps 2, 4, 6 and 7.
    assert topic == "/fleet/b/path" and stamp == 7 and path.header.frame_id == "map"
    assert [p.header.stamp.nanosec for p in path.poses] == [2, 4, 6, 7]
    assert fleet.due(now=101.0) == []   # unchanged, and within the period
    fleet.pose("b", 8, 9.0, 9.0, 0.0, joined=False)   # the join is split
    fleet.pose("b", 9, 3.0, 3.0, 0.0, joined=True)
    (_, msgtype, _, data), = fleet.due(now=200.0)
    assert [p.pose.position.x for p in ros.store.deserialize_cdr(data, msgtype).poses] == [3.0]


def test_a_robots_fleet_channels_are_advertised_when_it_first_joins():
    from schemas import FleetPose
    from services.common.convert import planar_pose

    service = FoxgloveService(RuntimeConfig(), FoxgloveConfig(port=0, fleet=True), "test")
    try:
        client = service.open_client()
        assert "/fleet/a/pose" not in client.channels
        for seq, joined in enumerate([False, True, True]):
            service.on_fleet_pose(FleetPose(header=Header(seq=seq, stamp=Time.from_seconds(seq), robot="a", frame_id="map"),
                                            pose=planar_pose(seq, 0.0, 0.0), heading=0.0, experience_id=0, joined=joined))
        assert {"/fleet/a/pose", "/fleet/a/path"} <= set(client.channels)
        assert len(service.history.messages("/fleet/a/pose")) == 2 and len(service.history.messages("/fleet/a/path")) == 1
        late = service.open_client()   # a client that connects later has the channels from the start
        assert {"/fleet/a/pose", "/fleet/a/path"} <= set(late.channels)
    finally:
        service.teardown()


def test_a_route_asked_of_the_map_is_one_path_in_the_map_frame_and_the_newest_is_kept():
    from schemas import MapRoute, Point
    from services.common.convert import planar_pose
    from services.ros.foxglove import RunHistory, newest_only
    from services.ros2wire.messages import ROUTE_TOPIC

    service = FoxgloveService(RuntimeConfig(), FoxgloveConfig(port=0), "test")
    try:
        for goal in (2.0, 3.0):   # two routes asked: a late client gets the newest
            route = MapRoute(header=Header(seq=40, stamp=Time.from_seconds(4.0), frame_id="map"),
                             start=Point(x=0.0, y=0.0, z=0.0), goal=Point(x=goal, y=1.0, z=0.0), experiences=[0, 3, 7],
                             poses=[planar_pose(0.0, 0.0, 0.0), planar_pose(1.0, 0.5, 0.4), planar_pose(goal, 1.0, 1.2)],
                             length=3.0, found=True)
            service.on_map_route(route)
        (stamp, data), = service.history.messages(ROUTE_TOPIC)
    finally:
        service.teardown()
    path = service.ros.store.deserialize_cdr(data, "nav_msgs/msg/Path")
    assert stamp == 4_000_000_000 and path.header.frame_id == "map"
    assert [(p.pose.position.x, p.pose.position.y) for p in path.poses] == [(0.0, 0.0), (1.0, 0.5), (3.0, 1.0)]
    assert [2 * math.atan2(p.pose.orientation.z, p.pose.orientation.w) for p in path.poses] == pytest.approx([0.0, 0.4, 1.2])
    assert newest_only(ROUTE_TOPIC) and RunHistory(10).capacity([ROUTE_TOPIC]) == 1
