"""The live ROS 2 node's pure core (services/ros/projection.py): the path it rebuilds from the
map's experiences and each frame's placement on them (MapPose.placement), whichever order
map/pose and map/update reach it in."""

from __future__ import annotations

import numpy as np
import pytest

from tests.extras import require

require("rosbags", "ros")

from services.common.geometry import between, compose  # noqa: E402
from services.ros import projection  # noqa: E402
from services.ros2wire.messages import RosMessages  # noqa: E402

# A small map's life: frames 0-2 on experience 0, frame 3 on a new experience 1; at frame 4 a
# closure moves both experiences, and frame 4's pose is placed on experience 0 as moved.
MAP_POSES = {0: ((0.0, 0.0, 0.0), 0), 1: ((0.5, 0.0, 0.0), 0), 2: ((1.0, 0.1, 0.1), 0),
             3: ((2.0, 0.2, 0.1), 1), 4: ((0.3, -0.2, 0.05), 0)}
UPDATES = {0: [(0, 0.0, 0.0, 0.0)], 3: [(1, 2.0, 0.2, 0.1)], 4: [(0, 0.1, -0.1, 0.02), (1, 1.8, 0.1, 0.08)]}
# The corrected trajectory: each frame on its experience as finally placed, at the offset the
# map gave it at its own frame.
EXPERIENCE_AT = {0: (0.0, 0.0, 0.0), 1: (2.0, 0.2, 0.1)}
FINAL = {0: (0.1, -0.1, 0.02), 1: (1.8, 0.1, 0.08)}


def placement(seq: int) -> tuple[int, tuple[float, float, float]]:
    """Where the map puts frame `seq`: its experience, and the offset from the experience as the
    map had it at that frame (frame 4 placed after the move)."""
    pose, experience = MAP_POSES[seq]
    return experience, between(FINAL[0] if seq == 4 else EXPERIENCE_AT[experience], pose)


def expected_path():
    return np.array([compose(FINAL[placement(seq)[0]], placement(seq)[1]) for seq in MAP_POSES])


def run(events, placed: bool = True) -> np.ndarray:
    live = projection.Projection(RosMessages("jazzy"))
    for kind, seq in events:
        if kind == "pose":
            pose, experience = MAP_POSES[seq]
            live.map_pose(seq, seq * 10**8, pose, experience, placement(seq) if placed else None)
        else:
            live.map_update(seq * 10**8, UPDATES[seq], [])
    return np.array([pose[1:] for pose in live.trajectory()])


def test_path_is_the_frames_on_their_experiences_as_the_map_now_has_them():
    # Each frame's update, then its pose: the order expmap publishes them in.
    events = [e for seq in MAP_POSES for e in ([("update", seq)] if seq in UPDATES else []) + [("pose", seq)]]
    path = run(events)
    assert path == pytest.approx(expected_path())
    assert path[4] == pytest.approx(MAP_POSES[4][0]) and path[2] != pytest.approx(MAP_POSES[2][0])   # moved with its experience


@pytest.mark.parametrize("late", [3, 4])
def test_an_update_reaching_the_node_after_its_frames_pose_gives_the_same_path(late):
    # Zenoh keeps each key's order, not the order between map/update and map/pose.
    events = []
    for seq in MAP_POSES:
        if seq in UPDATES and seq != late:
            events.append(("update", seq))
        events.append(("pose", seq))
        if seq == late:
            events.append(("update", seq))
    assert run(events) == pytest.approx(expected_path())


def test_every_update_after_every_pose_gives_the_same_path():
    events = [("pose", seq) for seq in MAP_POSES] + [("update", seq) for seq in UPDATES]
    assert run(events) == pytest.approx(expected_path())


def test_a_pose_without_a_placement_is_placed_against_its_experience_as_last_heard():
    # (a localisation on a saved map, which moves no experience): in the order expmap publishes
    events = [e for seq in MAP_POSES for e in ([("update", seq)] if seq in UPDATES else []) + [("pose", seq)]]
    assert run(events, placed=False) == pytest.approx(expected_path())
    # heard before its experience was announced, a frame is where its pose put it
    lone = projection.Projection(RosMessages("jazzy"))
    lone.map_pose(0, 0, (1.0, 2.0, 0.3), 7)
    assert lone.trajectory() == [pytest.approx((0, 1.0, 2.0, 0.3))]


def test_a_pose_sent_again_is_not_published_twice_and_a_new_run_starts_the_odometry_afresh():
    from services.common.recovery import REPLAY_FRAMES

    state = projection.Projection(RosMessages())
    for seq in range(100, 110):
        assert state.grid_pose(seq, seq, (0.1 * seq, 0.0, 0.0))
        assert state.map_pose(seq, seq, (0.1 * seq, 0.0, 0.0), 0, (0, (0.1 * seq, 0.0, 0.0)))
    # Frames the source re-sent after a stall, the stages' kept outputs, even from before the first heard.
    for seq in (105, 109, 109 - REPLAY_FRAMES):
        assert state.grid_pose(seq, seq, (9.0, 9.0, 0.0)) == [] and state.map_pose(seq, seq, (9.0, 9.0, 0.0), 0) == []
    assert state.odom_pose == (10.9, 0.0, 0.0) and len(state.frames) == 10
    assert state.grid_pose(0, 0, (0.0, 0.0, 0.0))   # far back: a new run of the robot
    assert state.odom_pose == (0.0, 0.0, 0.0) and state.frames == []
