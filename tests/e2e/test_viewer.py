"""`gridslam service viewer` as a real process around a real router, fed a short synthetic run:
the JSON it streams, and the page in a real headless Chromium (driven through chromedriver's
W3C WebDriver HTTP API with urllib).

The run: frames of the synthetic corridor world (mono, exact ground truth) on `camera/frame`,
its exact odometry with a small yaw bias on `egomotion` (so dead reckoning visibly drifts), a
real `gridcells` service turning that into `grid/pose` (and `grid/activity`), and a stand-in
for loop closure and the experience map (view templates, experiences every few frames,
loop closures on the second lap, map poses near the truth).

Set GRIDSLAM_UPDATE_SCREENSHOT=1 to write the screenshot to docs/img/viewer.png.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import threading
import time
import urllib.request

import numpy as np
import pytest
import zenoh

from schemas import (
    CameraFrame, EgoMotion, Experience, Header, Link, LoopClosure, MapPose, MapSnapshot, MapUpdate, PlanarIncrement,
    ServiceStatus, Time, ViewTemplate,
)
from services.common import codec, topics
from services.common.convert import image_to_msg, matrix_to_pose, planar_pose
from services.source.synthetic import SyntheticWorld, WorldConfig
from services.common.geometry import planar_from_camera
from tests.browser import Browser, chromium_and_driver
from tests.netutil import REPO, client_session, endpoint, free_port, port_open, start, start_router, stop, wait_for

pytestmark = pytest.mark.e2e

YAW_BIAS = 0.0015        # rad per frame added to the exact odometry: the dead reckoning drifts
EXPERIENCE_EVERY = 6      # frames between experiences of the stand-in map
SCREENSHOT = REPO / "docs" / "img" / "viewer.png"


@pytest.fixture(scope="module")
def world():
    # 0.25 m per frame: 150 frames a lap of the 37.4 m corridor loop, two laps.
    return SyntheticWorld(WorldConfig(seed=3, speed=0.25, laps=2), mono=True)


class ShortRun(threading.Thread):
    """Publishes a synthetic run at `fps` frames per second, as the upstream services would."""

    def __init__(self, session: zenoh.Session, world: SyntheticWorld, frames: int, fps: float):
        super().__init__(daemon=True)
        self.session, self.world, self.frames, self.fps = session, world, frames, fps
        self.published = 0
        self.halt = threading.Event()
        self.error: BaseException | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}

    def put(self, topic: str, message) -> None:
        publisher = self._publishers.get(topic)
        if publisher is None:
            publisher = self._publishers[topic] = self.session.declare_publisher(
                topics.key("robot0", topic), encoding=zenoh.Encoding(codec.encoding_of(message)),
                congestion_control=zenoh.CongestionControl.BLOCK)
        publisher.put(codec.encode(message))

    def run(self) -> None:
        try:
            self._run()
        except BaseException as error:  # reported by the test that started the run
            self.error = error

    def _run(self) -> None:
        experiences: list[tuple[float, float, int]] = []   # x, y, frame
        linked: set[tuple[int, int]] = set()
        current = 0   # the experience the robot is at
        last_closure = -100
        started = time.monotonic()
        for seq in range(self.frames):
            if self.halt.is_set():
                return
            frame = self.world[seq]
            header = Header(seq=seq, stamp=Time.from_seconds(frame.stamp), frame_id="camera", robot="robot0")
            self.put("camera/frame", CameraFrame(header=header, left=image_to_msg(frame.left),
                                                 ground_truth=matrix_to_pose(frame.ground_truth)))
            forward, left, yaw = frame.odometry
            self.put("egomotion", EgoMotion(header=header, increment=PlanarIncrement(forward=forward, left=left, yaw=yaw + YAW_BIAS),
                                            quality=1.0, estimator="passthrough"))
            x, y, heading = planar_from_camera(frame.ground_truth)
            x, y = x + 0.05 * math.sin(seq / 9), y + 0.05 * math.cos(seq / 13)   # a map close to, not on, the truth
            if seq % EXPERIENCE_EVERY == 0:
                near = [i for i, (ex, ey, f) in enumerate(experiences) if seq - f > 60 and math.hypot(ex - x, ey - y) < 0.8]
                new_experiences, new_links = [], []
                if near:   # a place seen on the first lap
                    matched = near[0]
                    self.put("view/template", ViewTemplate(header=header, template_id=matched, is_new=False, distance=0.03,
                                                           relative_angle=0.0, matched_frame=experiences[matched][2],
                                                           template_count=len(experiences)))
                    if seq - last_closure >= 4 * EXPERIENCE_EVERY:
                        last_closure = seq
                        self.put("loop/closure", LoopClosure(header=header, frame=seq, matched_frame=experiences[matched][2],
                                                             matched_template=matched, votes=5))
                        if current != matched and (current, matched) not in linked and (matched, current) not in linked:
                            new_links.append(Link(source=current, target=matched, dx=0.0, dy=0.0, dheading=0.0,
                                                  frame=seq, loop_closure=True))
                    current = matched
                else:
                    experiences.append((x, y, seq))
                    new_experiences.append(Experience(id=len(experiences) - 1, x=x, y=y, heading=heading,
                                                      template_id=len(experiences) - 1, frame=seq))
                    if len(experiences) > 1:
                        new_links.append(Link(source=current, target=len(experiences) - 1,
                                              dx=EXPERIENCE_EVERY * 0.25, dy=0.0, dheading=0.0, frame=seq))
                    current = len(experiences) - 1
                    self.put("view/template", ViewTemplate(header=header, template_id=len(experiences) - 1, is_new=True,
                                                           distance=0.2, relative_angle=0.0, matched_frame=seq,
                                                           template_count=len(experiences)))
                linked.update((link.source, link.target) for link in new_links)
                self.put("map/update", MapUpdate(header=header, experiences=new_experiences, links=new_links,
                                                 experience_count=len(experiences), link_count=len(linked)))
            self.put("map/pose", MapPose(header=header, pose=planar_pose(x, y, heading), heading=heading,
                                         experience_id=current))
            self.published = seq + 1
            delay = started + (seq + 1) / self.fps - time.monotonic()
            if delay > 0:
                self.halt.wait(delay)


class Pipeline:
    """A router, the viewer and gridcells as processes; a client session to publish with."""

    def __init__(self, integrator: str):
        self.port, self.http_port = free_port(), free_port()
        self.router = start_router(self.port)
        self.processes = [self.router]
        self.viewer = self._start(["service", "viewer", "-e", endpoint(self.port), "--http", f"127.0.0.1:{self.http_port}",
                                   "--instance", "e2e"])
        self._start(["service", "gridcells", "--integrator", integrator, "-e", endpoint(self.port), "--instance", "e2e"])
        self.session = client_session(self.port)
        self.url = f"http://127.0.0.1:{self.http_port}/"
        for service in ("viewer", "gridcells"):
            wait_for(lambda: any(r.ok for r in self.session.liveliness().get(
                f"{topics.PREFIX}/robot0/health/{service}/e2e", timeout=1)), timeout=20)

    def _start(self, args: list[str]) -> subprocess.Popen:
        process = start(args)
        self.processes.append(process)
        return process

    def state(self) -> dict:
        with urllib.request.urlopen(self.url + "state.json", timeout=5) as response:
            return json.loads(response.read())

    def close(self) -> None:
        self.session.close()
        for process in reversed(self.processes):
            stop(process)


def read_event(response) -> dict:
    while True:
        line = response.readline()
        assert line, "the event stream ended"
        if line.startswith(b"data: "):
            return json.loads(line[6:])


def follow(stream, last_frame: int) -> tuple[dict[str, list], list[int]]:
    """Read one event stream until `last_frame`: the points of every track, and the frame counters seen."""
    points: dict[str, list] = {}
    frames = []
    while not frames or frames[-1] < last_frame:
        event = read_event(stream)
        if event["counters"]["frame"] is not None:
            frames.append(event["counters"]["frame"])
        for stage, track in event["tracks"].items():
            assert track["from"] == len(points.setdefault(stage, []))   # tails continue what was sent
            points[stage] += track["points"]
    return points, frames


def test_viewer_process_streams_a_run_and_stops_on_sigterm(world):
    pipeline = Pipeline("deadreckoning")
    run = ShortRun(pipeline.session, world, frames=60, fps=60)
    try:
        # Two browsers watch at once; each gets the whole run.
        with urllib.request.urlopen(pipeline.url + "events", timeout=10) as stream, \
                urllib.request.urlopen(pipeline.url + "events", timeout=10) as second:
            run.start()
            other: dict = {}
            reader = threading.Thread(target=lambda: other.update(result=follow(second, 59)), daemon=True)
            reader.start()
            points, frames = follow(stream, 59)
            reader.join(timeout=10)
        assert len(set(frames)) > 3 and frames == sorted(frames)   # the frame counter advances, never back
        # Every drawn point arrived: ground truth may skip (camera frames are newest-only), poses may not.
        assert len(points["grid"]) == len(points["egomotion"]) == len(points["map"]) == 60
        assert 10 < len(points["ground_truth"]) <= 60
        assert other["result"][0]["grid"] == points["grid"]
        # The viewer's dead reckoning of `egomotion` is the gridcells dead-reckoning integrator's path.
        assert np.allclose(points["egomotion"], points["grid"], atol=2e-3)
        truth_end = planar_from_camera(world[59].ground_truth)[:2]
        assert np.allclose(points["ground_truth"][-1], truth_end, atol=2e-3)
        assert math.dist(points["egomotion"][-1], truth_end) > 0.1   # the yaw bias shows
        run.join(timeout=10)
        assert run.error is None

        def final_state():
            state = pipeline.state()
            received = {row["service"]: row.get("received", 0) for row in state["services"]}
            return received.get("gridcells", 0) >= 60 and received.get("viewer", 0) >= 3 * 60 and state

        state = wait_for(final_state, timeout=5)
        assert state["counters"]["experiences"] == 10 and len(state["map"]["experiences"]) == 10
        assert state["counters"]["latency_stage"] == "map" and state["counters"]["latency_ms"] is not None
        rows = {row["service"]: row for row in state["services"]}
        assert rows["viewer"]["alive"] and rows["gridcells"]["alive"] and rows["gridcells"]["gaps"] == 0
        assert rows["viewer"]["gaps"] == 0   # sparse and newest-only topics skip frames by design
        assert state["counters"]["decode_errors"] == 0

        # An update that says the map is bigger than what the viewer holds makes it query map/snapshot.
        snapshot = MapSnapshot(header=Header(seq=61, stamp=Time.from_seconds(6.1), robot="robot0"),
                               experiences=[Experience(id=i, x=float(i), y=-1.0, heading=0.0, template_id=i, frame=i)
                                            for i in range(12)], links=[])
        queries = []

        def answer(query):
            queries.append(str(query.key_expr))
            query.reply(query.key_expr, codec.encode(snapshot), encoding=zenoh.Encoding(codec.encoding_of(snapshot)))

        queryable = pipeline.session.declare_queryable(topics.key("robot0", "map/snapshot"), answer)
        run.put("map/update", MapUpdate(header=Header(seq=60, stamp=Time.from_seconds(6.0), robot="robot0"),
                                        experiences=[], links=[], experience_count=12, link_count=9))
        state = wait_for(lambda: (s := pipeline.state()) and len(s["map"]["experiences"]) == 12 and s, timeout=5)
        assert queries and state["map"]["experiences"][11] == [11, 11.0, -1.0] and state["counters"]["experiences"] == 12
        queryable.undeclare()

        # SIGTERM with a browser still connected: out within 2 s, exit 0, the port closed.
        with urllib.request.urlopen(pipeline.url + "events", timeout=10) as stream:
            read_event(stream)
            started = time.monotonic()
            pipeline.viewer.send_signal(signal.SIGTERM)
            code = pipeline.viewer.wait(timeout=5)
            elapsed = time.monotonic() - started
        assert code == 0 and elapsed < 2.0, pipeline.viewer.stderr.read()
        assert not port_open(pipeline.http_port)
    finally:
        run.halt.set()
        pipeline.close()


# ---------------------------------------------------------------------- a real browser
# What the page shows, read from its DOM: counters, drawn points per path, images, health rows.
PAGE = """
const count = (id) => Number(document.getElementById(id).dataset.count || 0);
const box = document.getElementById('track-grid').getBBox();
return {
  frame: document.getElementById('frame').textContent,
  updates: Number(document.body.dataset.updates || 0),
  connection: document.getElementById('connection').textContent,
  grid: count('track-grid'), egomotion: count('track-egomotion'), map: count('track-map'),
  ground_truth: count('track-ground_truth'), experiences: count('experience-dots'), loops: count('loop-links'),
  grid_box: [box.width, box.height],
  lattice: document.getElementById('lattice').naturalWidth, camera: document.getElementById('camera').naturalWidth,
  camera_caption: document.getElementById('camera-caption').textContent,
  lattice_caption: document.getElementById('lattice-caption').textContent,
  services: [...document.querySelectorAll('#health tbody tr')].map((row) => row.children[1].textContent),
  loop_closures: document.getElementById('loop-closures').textContent,
  // [scrollWidth, clientWidth] of the side panel and of the page: equal when nothing scrolls sideways.
  aside_width: [document.querySelector('aside').scrollWidth, document.querySelector('aside').clientWidth],
  page_width: [document.documentElement.scrollWidth, window.innerWidth],
};
"""


def test_browser_shows_the_run(world, tmp_path):
    chromium, chromedriver = chromium_and_driver()
    pipeline = Pipeline("grid")
    browser = None
    run = ShortRun(pipeline.session, world, frames=len(world), fps=30)
    try:
        browser = Browser(chromium, chromedriver, tmp_path / "profile")
        browser.open(pipeline.url)
        assert browser.script(PAGE)["frame"] == "–"   # nothing published yet
        run.start()
        page = wait_for(lambda: (p := browser.script(PAGE)) and p["grid"] >= 20 and p["frame"].isdigit() and p, timeout=20, period=0.2)
        assert page["connection"] == "live" and page["egomotion"] >= 20 and page["ground_truth"] >= 5
        # The frame counter advances while the run goes on, and the path grows.
        later = wait_for(lambda: (p := browser.script(PAGE)) and int(p["frame"]) >= int(page["frame"]) + 10 and p,
                         timeout=10, period=0.2)
        assert later["grid"] > page["grid"] and later["updates"] > page["updates"]
        run.join(timeout=30)
        assert run.error is None and run.published == len(world)
        end = wait_for(lambda: (p := browser.script(PAGE)) and p["frame"] == str(len(world) - 1) and p["loops"] >= 1 and p,
                       timeout=15, period=0.2)
        # The path spans the corridor loop (12 m × 8 m) on screen, not a dot; the map, the lattice
        # and the camera are drawn; the health table lists the services.
        assert end["grid_box"][0] > 200 and end["grid_box"][1] > 100
        assert end["experiences"] >= 20 and int(end["loop_closures"]) >= 1
        assert end["lattice"] == 64 and end["camera"] == 320
        assert "template" in end["camera_caption"] and "shift" in end["lattice_caption"]
        assert {"viewer", "gridcells"} <= set(end["services"])
        time.sleep(0.5)   # the last image loads
        target = SCREENSHOT if os.environ.get("GRIDSLAM_UPDATE_SCREENSHOT") == "1" else tmp_path / "viewer.png"
        target.parent.mkdir(parents=True, exist_ok=True)
        png = browser.screenshot()
        target.write_bytes(png)
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
        # A long run's widest row: an eleven-letter service, a host-pid instance, seven-digit counters.
        wide = ServiceStatus(header=Header(seq=0, stamp=Time.from_seconds(time.time())), service="loopclosure",
                             instance="robot-computer-123456", state="running", received=1234567, published=1234567,
                             decode_errors=0, gaps=0, stale=0, uptime=12345.6)
        pipeline.session.put(topics.status_key("robot0", "loopclosure", wide.instance), codec.encode(wide),
                             encoding=codec.encoding_of(ServiceStatus))
        wide_page = wait_for(lambda: (p := browser.script(PAGE)) and "loopclosure" in p["services"] and p, timeout=10, period=0.2)
        # The services table fits the 1400-pixel window: no horizontal scroll bar.
        assert wide_page["aside_width"][0] <= wide_page["aside_width"][1], wide_page
        assert wide_page["page_width"][0] <= wide_page["page_width"][1], wide_page
        # The viewer stops (as `gridslam run --view` stops it on Ctrl-C): the page keeps its last
        # images, even when a newer revision is asked for after the viewer has gone.
        stop(pipeline.viewer)
        browser.script("loadImage(document.getElementById('camera'), 'camera.jpg?r=999999');"
                       "loadImage(document.getElementById('lattice'), 'lattice.png?r=999999');")
        time.sleep(1.0)
        after = browser.script(PAGE)
        assert after["lattice"] == 64 and after["camera"] == 320, after
    finally:
        run.halt.set()
        if browser is not None:
            browser.close()
        pipeline.close()
