"""The viewer's state (numbers in, the page's JSON out), its config, and its HTTP endpoints
served in-process (no Zenoh: the adapter's handlers are called with real messages)."""

import json
import math
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from schemas import CameraFrame, GridPose, MapPose
from services.common.convert import image_to_msg, planar_pose
from services.common.errors import ConfigError
from services.common.geometry import planar_from_camera
from services.common.runtime import RuntimeConfig
from services.viewer.config import ViewerConfig
from services.common.service import Subscription
from services.viewer.service import INBOX_SIZE, ViewerService
from services.common.images import display_image, encode_camera_jpeg
from services.viewer.state import Cursor, ViewerParams, ViewerState, encode_lattice_png
from tests.messages import header, sample_messages


def camera_pose(forward: float, left: float, yaw: float) -> np.ndarray:
    """Camera-convention pose (x right, y down, z forward) of a planar pose: a turn by `yaw`
    counter-clockwise seen from above is a rotation by −yaw about the camera's y (down) axis."""
    c, s = math.cos(-yaw), math.sin(-yaw)
    matrix = np.eye(4)
    matrix[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    matrix[:3, 3] = [-left, 0.0, forward]
    return matrix


def as_json(state: ViewerState, now: float, cursor: Cursor | None = None, **options) -> dict:
    """The state as the browser gets it: through JSON."""
    return json.loads(json.dumps(state.view(now, cursor, **options)))


def status(decode_errors=0, gaps=0):
    return {"state": "running", "received": 5, "published": 5, "decode_errors": decode_errors, "gaps": gaps,
            "stale": 0, "uptime": 1.0}


# ---------------------------------------------------------------------- trajectories
def test_egomotion_is_dead_reckoned_as_se2_increments():
    state = ViewerState()
    for seq, (forward, yaw) in enumerate([(1.0, 0.0), (1.0, math.pi / 2), (1.0, 0.0)]):
        state.on_egomotion(seq, forward, 0.0, yaw, now=seq * 0.1)
    track = as_json(state, now=1.0)["tracks"]["egomotion"]
    # The step along the heading before the frame's yaw, then the yaw (the EgoMotion message's
    # SE(2) increment, as the gridcells service and the run's evaluation compose it).
    assert track["points"] == [[1.0, 0.0], [2.0, 0.0], [2.0, 1.0]]
    assert track["pose"][:2] == [2.0, 1.0] and track["pose"][2] == pytest.approx(math.pi / 2, abs=1e-4)


def test_ground_truth_is_shown_planar():
    assert planar_from_camera(camera_pose(2.0, 1.0, math.radians(30))) == pytest.approx((2.0, 1.0, math.radians(30)))
    state = ViewerState()
    state.on_camera_frame(4, None, camera_pose(3.0, -0.5, -0.2), now=0.0)
    track = as_json(state, now=0.0)["tracks"]["ground_truth"]
    assert track["points"] == [[3.0, -0.5]] and track["pose"] == [3.0, -0.5, -0.2] and track["seq"] == 4


def test_tails_send_only_new_points_and_thinning_resends_the_path():
    state = ViewerState(ViewerParams(max_points=4))
    cursor = Cursor()
    for seq in range(3):
        state.on_grid_pose(seq, float(seq), 0.0, 0.0, (0.0, 0.0), 1.0, False, "grid", now=0.0)
    first = as_json(state, 0.0, cursor)["tracks"]["grid"]
    assert first["from"] == 0 and [p[0] for p in first["points"]] == [0, 1, 2]
    state.on_grid_pose(3, 3.0, 0.0, 0.0, (0.0, 0.0), 1.0, False, "grid", now=0.0)
    second = as_json(state, 0.0, cursor)["tracks"]["grid"]
    assert second["from"] == 3 and second["points"] == [[3.0, 0.0]] and second["epoch"] == first["epoch"]
    # A fifth point exceeds max_points: every other point is kept, a new epoch sends it all.
    state.on_grid_pose(4, 4.0, 0.0, 0.0, (0.0, 0.0), 1.0, False, "grid", now=0.0)
    third = as_json(state, 0.0, cursor)["tracks"]["grid"]
    assert third["epoch"] == first["epoch"] + 1 and third["from"] == 0 and [p[0] for p in third["points"]] == [0, 2, 4]
    for seq in range(5, 8):   # stride 2 now: only even samples are drawn, the pose follows every one
        state.on_grid_pose(seq, float(seq), 0.0, 0.0, (0.0, 0.0), 1.0, False, "grid", now=0.0)
    fourth = as_json(state, 0.0, cursor)["tracks"]["grid"]
    assert fourth["points"] == [[6.0, 0.0]] and fourth["from"] == 3 and fourth["pose"][0] == 7.0
    assert as_json(state, 0.0, cursor)["tracks"]["grid"]["points"] == []
    state.on_grid_pose(8, 8.0, 0.0, 0.0, (0.0, 0.0), 1.0, False, "grid", now=0.0)
    fifth = as_json(state, 0.0, cursor)["tracks"]["grid"]
    assert fifth["from"] == 0 and [p[0] for p in fifth["points"]] == [0, 4, 8] and fifth["epoch"] == third["epoch"] + 1


def test_a_new_run_restarts_tracks_and_the_frame_counter():
    state = ViewerState()
    cursor = Cursor()
    for seq in range(100, 103):
        state.on_camera_frame(seq, None, camera_pose(seq, 0.0, 0.0), now=seq * 0.1)
        state.on_egomotion(seq, 1.0, 0.0, 0.0, now=seq * 0.1)
    # Frames sent again (the source re-sent its frames in flight; the stages' kept outputs) are drawn already.
    state.on_camera_frame(101, None, camera_pose(9.0, 9.0, 0.0), now=5.5)
    state.on_egomotion(101, 5.0, 0.0, 0.0, now=5.5)
    view = as_json(state, 6.0, cursor)
    assert view["counters"]["frame"] == 102 and view["tracks"]["egomotion"]["points"] == [[1.0, 0.0], [2.0, 0.0], [3.0, 0.0]]
    assert [p[0] for p in view["tracks"]["ground_truth"]["points"]] == [100.0, 101.0, 102.0]
    state.on_camera_frame(0, None, camera_pose(0.0, 0.0, 0.0), now=6.0)
    state.on_egomotion(0, 0.5, 0.0, 0.0, now=6.0)
    view = as_json(state, 6.0, cursor)
    assert view["counters"]["frame"] == 0
    assert view["tracks"]["ground_truth"]["from"] == 0 and view["tracks"]["ground_truth"]["points"] == [[0.0, 0.0]]
    assert view["tracks"]["egomotion"]["from"] == 0 and view["tracks"]["egomotion"]["points"] == [[0.5, 0.0]]


# ---------------------------------------------------------------------- counters
def test_counters_frame_rate_latency_and_totals():
    state = ViewerState()
    for seq in range(21):   # 20 frames per second; grid pose 30 ms and map pose 50 ms after the frame
        t = seq * 0.05
        state.on_camera_frame(seq, None, None, now=t)
        state.on_grid_pose(seq, 0.1 * seq, 0.0, 0.0, (1.0, 0.0), 0.1, seq == 20, "grid", now=t + 0.03)
        if seq >= 10:
            state.on_map_pose(seq, 0.1 * seq, 0.0, 0.0, 3, now=t + 0.05)
    state.on_loop_closure(frame=20, matched_frame=2, matched_template=1, votes=7)
    state.on_view_template(20, template_id=1, is_new=False, distance=0.04, matched_frame=2, template_count=9)
    # Links by kind: odometric, a closure the map kept, one it refused (not counted as a closure link).
    state.on_map_update(20, [(0, 0.0, 0.0), (1, 1.0, 0.0), (2, 5.0, 0.0)], [(0, 1, 0), (1, 0, 1), (2, 0, 2)], 3, 3)
    state.on_liveliness("gridcells", "a", True)
    state.on_liveliness("viewer", "v", True)
    state.on_liveliness("egomotion", "b", False)
    state.on_status("gridcells", "a", status(decode_errors=2, gaps=3), now=1.0)
    state.on_status("viewer", "v", status(decode_errors=1, gaps=40), now=1.0)
    counters = as_json(state, now=1.05)["counters"]
    assert counters["frame"] == 20 and counters["rate_hz"] == pytest.approx(20.0)
    assert counters["latency_stage"] == "map" and counters["latency_ms"] == pytest.approx(50.0)
    assert counters["loop_closures"] == 1 and counters["loop_closure_links"] == 1
    assert counters["experiences"] == 3 and counters["templates"] == 9 and counters["saturations"] == 1
    # Decode errors of every service; gaps of the pipeline only (a viewer skips frames on purpose).
    assert counters["decode_errors"] == 3 and counters["gaps"] == 3 and counters["services_alive"] == 2
    assert as_json(state, now=10.0)["counters"]["rate_hz"] == 0.0   # stalled: no frames in the window
    rows = {row["service"]: row for row in as_json(state, now=5.0)["services"]}
    assert rows["gridcells"]["silent"] and not rows["egomotion"]["alive"] and not rows["egomotion"]["silent"]
    assert not state.service_rows(now=2.0)[1]["silent"] and rows["gridcells"]["gaps"] == 3


def test_a_run_is_finished_when_the_source_says_so_and_its_stopped_services_are_not_dead():
    state = ViewerState()
    for seq in range(100, 105):
        state.on_camera_frame(seq, None, None, now=0.001 * seq)
        state.on_grid_pose(seq, 0.1 * seq, 0.0, 0.0, (1.0, 0.0), 0.1, False, "grid", now=0.001 * seq)
    for service in ("source", "gridcells", "egomotion"):
        state.on_liveliness(service, service, True)
    state.on_status("source", "source", {**status(), "extra": {"frames_sent": 5}}, now=0.5)
    assert as_json(state, now=0.6)["counters"]["finished"] is None   # frames sent, not yet all done
    # The source's last status as it stops: every frame acknowledged; then the runner stops the stages.
    state.on_status("source", "source", {**status(), "state": "stopping", "extra": {"frames_sent": 5, "finished": 1}},
                    now=0.7)
    state.on_status("gridcells", "gridcells", {**status(), "state": "stopping"}, now=0.8)
    for service in ("source", "gridcells", "egomotion"):
        state.on_liveliness(service, service, False)
    view = as_json(state, now=60.0)
    assert view["counters"]["finished"] == {"frames": 5} and view["counters"]["frame"] == 104
    rows = {row["service"]: row for row in view["services"]}
    assert rows["source"]["stopped"] and rows["source"]["state"] == "stopped" and not rows["source"]["silent"]
    assert rows["gridcells"]["stopped"] and rows["gridcells"]["state"] == "stopped"
    # Gone without saying it was stopping (its last status said running, or none came): not stopped.
    assert not rows["egomotion"]["stopped"] and "state" not in rows["egomotion"]
    # The next run on the robot (seq far back, at 0) is not finished.
    state.on_camera_frame(0, None, None, now=61.0)
    assert as_json(state, now=61.0)["counters"]["finished"] is None


def test_latency_falls_back_to_grid_without_a_map():
    state = ViewerState()
    state.on_camera_frame(1, None, None, now=1.0)
    state.on_grid_pose(1, 0.0, 0.0, 0.0, (0.0, 0.0), 0.0, False, "grid", now=1.012)
    counters = state.counters(now=1.1)
    assert counters["latency_stage"] == "grid" and counters["latency_ms"] == pytest.approx(12.0)


# ---------------------------------------------------------------------- map
def test_map_is_sent_when_changed_and_snapshots_merge_by_age():
    state = ViewerState()
    cursor = Cursor()
    missing = state.on_map_update(10, [(5, 1.0, 2.0)], [(4, 5, False)], experience_count=6, link_count=5)
    assert missing   # experiences 0..4 were never seen: the adapter asks for a snapshot
    assert as_json(state, 0.0, cursor)["map"]["experiences"] == [[5, 1.0, 2.0]]
    assert "map" not in as_json(state, 0.0, cursor)
    # An older snapshot fills in what is missing but does not undo the newer update.
    state.on_map_snapshot(8, [(i, float(i), 0.0) for i in range(6)], [(i, i + 1, i == 4) for i in range(5)])
    view = as_json(state, 0.0, cursor, include_map=False)
    assert "map" not in view
    view = as_json(state, 0.0, cursor)
    assert view["map"]["experiences"][5] == [5, 1.0, 2.0] and len(view["map"]["experiences"]) == 6
    assert [4, 5, 0] in view["map"]["links"] and view["counters"]["experiences"] == 6
    # A newer snapshot replaces everything (relaxation moved the experiences).
    state.on_map_snapshot(12, [(i, 2.0 * i, 1.0) for i in range(6)], [(i, i + 1, False) for i in range(5)])
    view = as_json(state, 0.0, cursor)
    assert view["map"]["experiences"][5] == [5, 10.0, 1.0] and [4, 5, 0] in view["map"]["links"]
    assert not state.on_map_update(13, [(6, 1.0, 1.0)], [(5, 6, False)], experience_count=7, link_count=6)


def test_the_last_route_asked_of_the_map_is_drawn_with_it():
    state = ViewerState()
    cursor = Cursor()
    state.on_map_update(3, [(0, 0.0, 0.0), (1, 1.0, 0.0)], [(0, 1, False)], experience_count=2, link_count=1)
    assert as_json(state, 0.0, cursor)["map"]["route"] == []
    state.on_route([(0.0, 0.0), (1.0, 0.0)])
    assert as_json(state, 0.0, cursor)["map"]["route"] == [[0.0, 0.0], [1.0, 0.0]]   # sent because it changed
    state.on_route([(1.0, 0.0)])
    assert as_json(state, 0.0, cursor)["map"]["route"] == [[1.0, 0.0]]


# ---------------------------------------------------------------------- images
def test_images_are_offered_once_per_revision():
    state = ViewerState()
    cursor = Cursor()
    grey = np.full((480, 640), 90, np.uint8)
    state.on_camera_frame(3, display_image(grey, "mono8", 320), None, now=0.0)
    state.on_grid_activity(3, np.arange(64 * 64, dtype=np.uint8).reshape(64, 64) % 251, (1.25, -0.5), 128, 2.5)
    view = as_json(state, 0.0, cursor)
    assert view["camera"] == {"revision": 1, "seq": 3, "size": [320, 240]}
    assert view["lattice"]["shift"] == [1.25, -0.5] and view["lattice"]["size"] == [64, 64]
    again = as_json(state, 0.0, cursor)
    assert "camera" not in again and "lattice" not in again
    state.on_camera_frame(4, display_image(grey, "mono8", 320), None, now=0.1)
    assert "camera" not in as_json(state, 0.0, cursor, include_images=False)
    assert as_json(state, 0.0, cursor)["camera"]["seq"] == 4
    json.dumps(as_json(state, 0.0))   # everything the page gets is plain JSON


def test_display_image_converts_and_downsamples():
    rgb = np.zeros((100, 200, 3), np.uint8)
    rgb[..., 0] = 255   # red in RGB
    bgr = display_image(rgb, "rgb8", 100)
    assert bgr.shape == (50, 100, 3) and bgr[0, 0].tolist() == [0, 0, 255]
    assert display_image(np.full((10, 10), 0x4000, np.uint16), "mono16", 100)[0, 0] == 0x40
    depth = display_image(np.array([[1.0, 3.0], [np.nan, 2.0]], np.float32), "32FC1", 100)
    assert depth.dtype == np.uint8 and depth[0, 1] == 255 and depth[0, 0] < depth[1, 1] < depth[0, 1]
    jpeg = cv2.imdecode(np.frombuffer(encode_camera_jpeg(bgr), np.uint8), cv2.IMREAD_COLOR)
    assert jpeg.shape == (50, 100, 3) and jpeg[25, 50, 2] > 200
    lattice = np.zeros((16, 16), np.uint8)
    lattice[8, 8] = 255
    png = cv2.imdecode(np.frombuffer(encode_lattice_png(lattice), np.uint8), cv2.IMREAD_COLOR)
    assert png.shape == (16, 16, 3) and png[8, 8].sum() > png[0, 0].sum()


# ---------------------------------------------------------------------- config
def test_config_binds_loopback_unless_remote_is_allowed():
    assert ViewerConfig().address == ("127.0.0.1", 8080)
    assert ViewerConfig(http="[::1]:0").address == ("::1", 0)
    assert ViewerConfig(http="localhost:9000").address == ("localhost", 9000)
    with pytest.raises(ValueError, match="allow-remote"):
        ViewerConfig(http="0.0.0.0:8080")
    assert ViewerConfig(http="0.0.0.0:8080", allow_remote=True).address == ("0.0.0.0", 8080)
    with pytest.raises(ValueError, match="HOST:PORT"):
        ViewerConfig(http="8080")


# ---------------------------------------------------------------------- the adapter's HTTP side, in-process
@pytest.fixture
def viewer():
    service = ViewerService(RuntimeConfig(), ViewerConfig(http="127.0.0.1:0", rate_hz=20, max_clients=1), "unit")
    service.start_http()
    yield service
    service.close_http()


def get(url: str, host: str | None = None) -> tuple[int, bytes, str]:
    request = urllib.request.Request(url, headers={"Host": host} if host else {})
    try:
        with urllib.request.urlopen(request, timeout=5) as response:
            return response.status, response.read(), response.headers.get("Content-Type", "")
    except urllib.error.HTTPError as error:
        return error.code, b"", ""


def test_http_serves_the_page_state_images_and_refuses_foreign_hosts(viewer):
    status_code, page, content_type = get(viewer.url)
    assert status_code == 200 and b"viewer.js" in page and content_type.startswith("text/html")
    assert get(viewer.url + "camera.jpg")[0] == 204   # nothing yet
    messages = {type(m).__name__: m for m in sample_messages(seq=3)}
    viewer.on_camera_frame(messages["CameraFrame"])
    viewer.on_grid_pose(messages["GridPose"])
    viewer.on_grid_activity(messages["GridActivity"])
    viewer.on_map_update(messages["MapUpdate"])
    state = json.loads(get(viewer.url + "state.json")[1])
    assert state["tracks"]["grid"]["points"] == [[3.0, -1.0]] and state["counters"]["frame"] == 3
    assert state["tracks"]["ground_truth"]["seq"] == 3 and len(state["map"]["experiences"]) == 2
    status_code, jpeg, content_type = get(viewer.url + "camera.jpg")
    assert status_code == 200 and content_type == "image/jpeg"
    assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED).shape[:2] == (24, 32)
    assert get(viewer.url + "lattice.png")[2] == "image/png"
    assert get(viewer.url + "state.json", host="attacker.example:80")[0] == 403   # DNS rebinding
    assert get(viewer.url + "nothing")[0] == 404


def read_events(response, count: int) -> list[dict]:
    events = []
    while len(events) < count:
        line = response.readline()
        assert line, "stream ended"
        if line.startswith(b"data: "):
            events.append(json.loads(line[6:]))
    return events


def test_event_stream_sends_tails_and_frees_its_slot(viewer):
    def pose(seq):
        return GridPose(header=header(seq, "odom"), pose=planar_pose(0.5 * seq, 0.0, 0.0), heading=0.0,
                        lattice_shift=(1.0, 0.0), step_length=0.5, integrator="grid")

    viewer.on_grid_pose(pose(0))
    with urllib.request.urlopen(viewer.url + "events", timeout=5) as response:
        assert response.headers["Content-Type"] == "text/event-stream"
        first = read_events(response, 1)[0]
        assert first["tracks"]["grid"]["points"] == [[0.0, 0.0]] and first["counters"]["frame"] == 0
        assert get(viewer.url + "events")[0] == 503   # max_clients=1: a second stream is refused
        viewer.on_grid_pose(pose(1))
        viewer.on_map_pose(MapPose(header=header(1, "map"), pose=planar_pose(0.4, 0.1, 0.0), heading=0.0, experience_id=0))
        events = read_events(response, 1)
        while events[-1]["tracks"]["map"]["seq"] is None:   # the two poses may come in two updates
            events += read_events(response, 1)
        assert [p for e in events for p in e["tracks"]["grid"]["points"]] == [[0.5, 0.0]]
        assert events[0]["tracks"]["grid"]["from"] == 1 and events[-1]["tracks"]["grid"]["pose"] == [0.5, 0.0, 0.0]
        assert events[-1]["tracks"]["map"]["points"] == [[0.4, 0.1]] and events[-1]["counters"]["frame"] == 1
    # The browser went away: its slot is free again once the server notices (next write fails).
    for _ in range(50):
        viewer.on_grid_pose(pose(2 + _))
        try:
            with urllib.request.urlopen(viewer.url + "events", timeout=5) as response:
                assert read_events(response, 1)[0]["counters"]["frame"] >= 2
                break
        except urllib.error.HTTPError as error:
            assert error.code == 503
            viewer.http_stop.wait(0.05)
    else:
        pytest.fail("the closed stream's slot was never freed")


def test_a_busy_port_is_a_config_error(viewer):
    with pytest.raises(ConfigError, match="cannot serve on"):
        ViewerService(RuntimeConfig(), ViewerConfig(http=viewer.url.split("/")[2]))


def test_camera_frame_message_feeds_a_downsampled_image(viewer):
    wide = np.tile(np.arange(1280, dtype=np.uint16) % 256, (200, 1)).astype(np.uint8)
    frame = CameraFrame(header=header(9), left=image_to_msg(wide), ground_truth=planar_pose(0.0, 0.0, 0.0))
    viewer.on_camera_frame(frame)
    assert viewer.viewer_state.camera.shape == (50, 320)


def test_a_full_inbox_drops_instead_of_pushing_back(viewer):
    # Where the base service blocks Zenoh's delivery on a full inbox, the viewer drops and counts.
    subscription = Subscription("camera/frame", CameraFrame, lambda message: None, newest_only=True, drop_stale=False,
                                sparse=True)
    viewer._subscriptions.append(subscription)
    for _ in range(INBOX_SIZE):
        viewer._put((0, ("key", b"", "encoding")))
    started = time.monotonic()
    viewer._put((0, ("key", b"", "encoding")))
    subscription.pending = ("key", b"newest", "encoding")
    viewer._put((0, None))   # a newest-only marker that does not fit: the next sample must queue a new one
    assert time.monotonic() - started < 0.05 and viewer.counters.dropped_busy == 2 and subscription.pending is None
    assert viewer.status().extra["dropped_busy"] == 2   # shown in the viewer's row on the page
