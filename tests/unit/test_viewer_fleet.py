"""The viewer's fleet (services/viewer/fleet.py: numbers in, the page's JSON out), its setting,
and the adapter's handlers fed real fleet messages in-process (no Zenoh)."""

import argparse
import json
import urllib.request

import pytest

from schemas import FleetExperience, FleetLink, FleetPose, FleetRobot, FleetSnapshot, FleetUpdate, Header, Time
from services.common.config import load_config
from services.common.convert import planar_pose
from services.common.runtime import RuntimeConfig
from services.viewer import service as viewer_service
from services.viewer.config import ViewerConfig
from services.viewer.fleet import FleetCursor, FleetView
from services.viewer.service import ViewerService, fleet_items


def as_json(fleet: FleetView, cursor: FleetCursor | None = None, **options) -> dict:
    return json.loads(json.dumps(fleet.view(cursor, **options)))


def robots(**joined) -> list[dict]:
    return [{"name": name, "joined": flag, "joined_at": None if name == "a" or not flag else 7, "part": "a" if flag else name,
             "experiences": 2} for name, flag in joined.items()]


def test_each_robot_has_its_track_and_a_robot_not_joined_is_marked_and_restarted_on_joining():
    fleet = FleetView(max_points=100)
    for seq in range(3):
        fleet.on_pose("a", seq, seq * 1.0, 0.0, 0.0, seq, True)
        fleet.on_pose("b", 10 + seq, 5.0, seq * 0.5, 1.0, seq, False)   # in b's own part's frame
    state = as_json(fleet)
    assert state["robots"]["a"]["joined"] and state["robots"]["a"]["track"]["points"] == [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]
    b = state["robots"]["b"]
    assert not b["joined"] and b["track"]["points"] == [[5.0, 0.0], [5.0, 0.5], [5.0, 1.0]]
    epoch = b["track"]["epoch"]
    # b joins at its frame 13: its points in its own frame are dropped, the track goes on in the fleet frame.
    fleet.on_pose("b", 13, 40.0, 2.0, 1.0, 3, True)
    b = as_json(fleet)["robots"]["b"]
    assert b["joined"] and b["track"]["points"] == [[40.0, 2.0]] and b["track"]["epoch"] != epoch
    assert b["track"]["pose"] == [40.0, 2.0, 1.0] and b["experience_id"] == 3
    # A split (the fleet map undoes the join) starts it afresh again.
    fleet.on_robots(robots(a=True, b=False))
    assert as_json(fleet)["robots"]["b"]["track"]["points"] == [] and not as_json(fleet)["robots"]["b"]["joined"]


def test_a_pose_sent_again_is_dropped_and_a_new_run_starts_the_track_afresh():
    fleet = FleetView(max_points=100)
    for seq in range(100, 110):
        fleet.on_pose("a", seq, seq * 1.0, 0.0, 0.0, 0, True)
    epoch = as_json(fleet)["robots"]["a"]["track"]["epoch"]
    fleet.on_pose("a", 105, 999.0, 0.0, 0.0, 0, True)   # its source re-sent its frames in flight
    track = as_json(fleet)["robots"]["a"]["track"]
    assert len(track["points"]) == 10 and track["epoch"] == epoch and track["pose"][0] == 109.0
    fleet.on_pose("a", 0, 7.0, 0.0, 0.0, 0, True)       # far back: a new run of the robot
    track = as_json(fleet)["robots"]["a"]["track"]
    assert track["points"] == [[7.0, 0.0]] and track["epoch"] != epoch


def test_tails_send_only_new_points_per_robot():
    fleet = FleetView(max_points=100)
    cursor = FleetCursor()
    fleet.on_pose("a", 0, 0.0, 0.0, 0.0, 0, True)
    fleet.on_pose("a", 1, 1.0, 0.0, 0.0, 0, True)
    first = as_json(fleet, cursor)
    assert first["robots"]["a"]["track"]["from"] == 0 and len(first["robots"]["a"]["track"]["points"]) == 2
    fleet.on_pose("a", 2, 2.0, 0.0, 0.0, 1, True)
    fleet.on_pose("c", 0, 9.0, 9.0, 0.0, 0, True)
    second = as_json(fleet, cursor)
    assert second["robots"]["a"]["track"]["from"] == 2 and second["robots"]["a"]["track"]["points"] == [[2.0, 0.0]]
    assert second["robots"]["c"]["track"]["from"] == 0 and second["robots"]["c"]["track"]["points"] == [[9.0, 9.0]]


def test_updates_build_the_fleet_map_sent_only_when_changed_and_a_snapshot_replaces_it():
    fleet = FleetView()
    cursor = FleetCursor()
    fleet.on_update(robots(a=True, b=False), [("a", 0, 0.0, 0.0), ("a", 1, 1.0, 0.0), ("b", 0, 3.0, 3.0)],
                    [("b", 0, 0, "a", 1, "pending")])
    state = as_json(fleet, cursor)
    assert state["map"]["experiences"] == {"a": [[0, 0.0, 0.0], [1, 1.0, 0.0]], "b": [[0, 3.0, 3.0]]}
    assert state["map"]["links"] == [["b", 0, "a", 1, "pending"]]   # robot, experience, matched robot, experience
    assert state["closures"] == {"accepted": 0, "rejected": 0, "pending": 1, "unmeasured": 0}
    assert state["robots"]["b"]["part"] == "b" and not state["robots"]["b"]["joined"]
    assert "map" not in as_json(fleet, cursor)    # unchanged: not sent again
    # b joins: its experiences move into the fleet frame, the closure is accepted, another refused.
    fleet.on_update(robots(a=True, b=True), [("b", 0, 1.02, 0.01)],
                    [("b", 0, 0, "a", 1, "accepted"), ("b", 1, 0, "a", 0, "rejected")])
    state = as_json(fleet, cursor)
    assert state["map"]["experiences"]["b"] == [[0, 1.02, 0.01]] and state["robots"]["b"]["joined_at"] == 7
    assert state["closures"] == {"accepted": 1, "rejected": 1, "pending": 0, "unmeasured": 0}
    # A snapshot (a restarted fleet map) replaces the map: what it does not hold is gone.
    fleet.on_snapshot(robots(a=True), [("a", 0, 0.5, 0.0)], [])
    state = as_json(fleet, cursor)
    assert state["map"]["experiences"] == {"a": [[0, 0.5, 0.0]], "b": []} and state["map"]["links"] == []
    assert state["snapshots"] == 1 and state["closures"]["accepted"] == 0


def test_a_bad_point_limit_is_refused():
    with pytest.raises(ValueError, match="max_points"):
        FleetView(max_points=1)


def test_the_fleet_setting_is_declared_once_for_file_environment_and_flag(tmp_path, monkeypatch):
    assert ViewerConfig().fleet is False
    path = tmp_path / "gridslam.toml"
    path.write_text("[viewer]\nfleet = true\n")
    assert load_config(ViewerConfig, "viewer", config_file=path).fleet is True
    monkeypatch.setenv("GRIDSLAM_VIEWER_FLEET", "true")
    assert load_config(ViewerConfig, "viewer").fleet is True
    parser = argparse.ArgumentParser()
    viewer_service.add_arguments(parser)
    assert parser.parse_args(["--fleet"]).fleet is True and parser.parse_args([]).fleet is None
    assert "fleet frame" in parser.format_help()


# ---------------------------------------------------------------------- the adapter, in-process
def header(seq: int, robot: str) -> Header:
    return Header(seq=seq, stamp=Time.from_seconds(seq / 10), frame_id="map", robot=robot)


def fleet_pose(robot: str, seq: int, x: float, joined: bool) -> FleetPose:
    return FleetPose(header=header(seq, robot), pose=planar_pose(x, 1.0, 0.25), heading=0.25, experience_id=seq // 2,
                     joined=joined)


def fleet_update(joined_b: bool) -> FleetUpdate:
    return FleetUpdate(
        header=header(4, "b"),
        robots=[FleetRobot(name="a", joined=True, part="a", experiences=2),
                FleetRobot(name="b", joined=joined_b, joined_at=4 if joined_b else None, part="a" if joined_b else "b",
                           experiences=1)],
        experiences=[FleetExperience(robot="a", id=0, x=0.0, y=1.0, heading=0.0),
                     FleetExperience(robot="a", id=1, x=0.5, y=1.0, heading=0.0),
                     FleetExperience(robot="b", id=0, x=0.52, y=1.01, heading=0.0)],
        links=[FleetLink(robot="b", index=0, experience=0, matched_robot="a", matched_experience=1, fate="accepted")])


def test_fleet_items_read_the_messages_as_the_core_takes_them():
    robots_, experiences, links = fleet_items(fleet_update(True))
    assert robots_[1] == {"name": "b", "joined": True, "joined_at": 4, "part": "a", "experiences": 1}
    assert experiences[2] == ("b", 0, 0.52, 1.01) and links == [("b", 0, 0, "a", 1, "accepted")]
    snapshot = FleetSnapshot(header=header(0, "fleet"), robots=fleet_update(False).robots, experiences=[], links=[])
    assert fleet_items(snapshot)[0][1]["joined"] is False


@pytest.fixture
def fleet_viewer():
    service = ViewerService(RuntimeConfig(robot="a"), ViewerConfig(http="127.0.0.1:0", fleet=True), "unit")
    service.start_http()
    yield service
    service.close_http()


def test_the_state_json_carries_the_fleet_only_with_fleet(fleet_viewer):
    for seq in range(4):
        fleet_viewer.on_fleet_pose(fleet_pose("a", seq, seq * 0.25, True))
        fleet_viewer.on_fleet_pose(fleet_pose("b", seq, 7.0, seq >= 2))
    fleet_viewer.on_fleet_update(fleet_update(True))
    with urllib.request.urlopen(fleet_viewer.url + "state.json", timeout=5) as response:
        state = json.loads(response.read())
    fleet = state["fleet"]
    assert fleet["robots"]["a"]["track"]["points"] == [[0.0, 1.0], [0.25, 1.0], [0.5, 1.0], [0.75, 1.0]]
    assert fleet["robots"]["b"]["joined"] and fleet["robots"]["b"]["track"]["points"] == [[7.0, 1.0], [7.0, 1.0]]
    assert fleet["closures"]["accepted"] == 1 and fleet["map"]["experiences"]["b"] == [[0, 0.52, 1.01]]
    plain = ViewerService(RuntimeConfig(), ViewerConfig(http="127.0.0.1:0"), "unit")
    try:
        assert plain.fleet is None and "fleet" not in plain.view()
    finally:
        plain.close_http()
