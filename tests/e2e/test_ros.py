"""gridslam among ROS tools, end to end with the real command line:

- a run serves Foxglove live: a WebSocket client speaking the Foxglove protocol subscribes to
  /gridslam/map during the run and receives its poses;
- the finished run is served on until Ctrl-C: the run prints where (viewer and Foxglove), the
  npm `@foxglove/ws-protocol` client, offering only `foxglove.websocket.v1`, connects after the
  last frame and receives every channel of the run, a headless browser opening the viewer then
  shows the run finished, and SIGINT ends it all with exit code 0;
- the run's run.mcap, read back with the mcap reader and mcap-ros2-support: one Odometry per
  frame and stage equal to the TUM files, and the last MarkerArray's experiences equal to
  `gridslam map export`'s graph; `gridslam export mcap` writes it again from the folder;
- bags written here with rosbags from the same synthetic frames (ROS 1, ROS 2 sqlite3 and
  MCAP; mono and stereo; raw, PNG and JPEG) give the same trajectories as the synthetic source.
"""

from __future__ import annotations

import base64
import json
import signal
import struct
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from tests.extras import require

require("rosbags", "ros")
require("foxglove", "foxglove")
require("mcap_ros2", "test")
require("websockets", "test")

from mcap.reader import make_reader   # noqa: E402
from mcap_ros2.decoder import DecoderFactory   # noqa: E402
from websockets.sync.client import connect   # noqa: E402

from services.evaluation.trajectory import read_tum   # noqa: E402
from services.source import open_source   # noqa: E402
from services.ros2wire.messages import TOPICS   # noqa: E402
from tests import npm_foxglove   # noqa: E402
from tests.bags import ODOM, image_topic, write_bag   # noqa: E402
from tests.browser import Browser, chromium_and_driver   # noqa: E402
from tests.netutil import GRIDSLAM, REPO, endpoint, free_port, port_open, start, wait_for   # noqa: E402

pytestmark = pytest.mark.e2e

FRAMES = 40
# Scanline odometry reads the left image only, so one synthetic run is the reference for mono
# and stereo bags alike.
RUN = ["--preset", "synthetic", "--egomotion", "scanline", "--n-frames", str(FRAMES)]
STAGE_FILES = {"/gridslam/egomotion": "egomotion", "/gridslam/gridcells": "gridcells", "/gridslam/map": "map_online",
               "/gridslam/groundtruth": "groundtruth"}
COMPARED = ("egomotion", "gridcells", "map_online", "map")


def gridslam(args, timeout=300):
    done = subprocess.run(GRIDSLAM + args, cwd=REPO, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


class FoxgloveClient(threading.Thread):
    """Connects (retrying until the server is up), subscribes to one topic with the Foxglove
    WebSocket protocol, and keeps (receive time ns, payload) of every message until closed."""

    def __init__(self, port: int, topic: str):
        super().__init__(daemon=True)
        self.port, self.topic = port, topic
        self.advertised: dict | None = None
        self.messages: list[tuple[int, bytes]] = []
        self.halt = threading.Event()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self._run()
        except BaseException as error:   # noqa: BLE001 (reported by the test)
            self.error = error

    def _run(self) -> None:
        deadline = time.monotonic() + 120
        while True:
            try:
                socket = connect(f"ws://127.0.0.1:{self.port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                                 max_size=None, open_timeout=2)
                break
            except OSError:
                if time.monotonic() > deadline or self.halt.is_set():
                    raise
                time.sleep(0.2)
        with socket:
            while not self.halt.is_set():
                try:
                    frame = socket.recv(timeout=0.5)
                except TimeoutError:
                    continue
                except Exception:   # the server stopped with the run
                    return
                if isinstance(frame, str):
                    message = json.loads(frame)
                    if message["op"] == "advertise" and self.advertised is None:
                        channel = next((c for c in message["channels"] if c["topic"] == self.topic), None)
                        if channel is not None:
                            self.advertised = channel
                            socket.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel["id"]}]}))
                elif frame[0] == 0x01:   # message data: opcode, subscription id (u32), log time (u64), payload
                    _, log_time = struct.unpack_from("<IQ", frame, 1)
                    self.messages.append((log_time, bytes(frame[13:])))


def read_mcap(path):
    """{topic: [(log time, decoded message)]} of an MCAP file, in stamp order."""
    messages: dict[str, list] = {}
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            messages.setdefault(channel.topic, []).append((message.log_time, decoded))
    return messages


@dataclass
class ServedRun:
    """`gridslam run --foxglove PORT --view HOST:PORT` on recorded frames, still serving the
    finished run: its process, ports and output so far."""

    out: Path
    client: FoxgloveClient
    process: subprocess.Popen
    ports: dict[str, int]
    stdout: list[str] = field(default_factory=list)
    stderr: list[str] = field(default_factory=list)

    def read(self) -> None:
        for stream, lines in ((self.process.stdout, self.stdout), (self.process.stderr, self.stderr)):
            threading.Thread(target=lambda s=stream, kept=lines: kept.extend(s), daemon=True).start()


@pytest.fixture(scope="module")
def served_run(tmp_path_factory):
    """The reference run, served live to a Foxglove client subscribed to /gridslam/map, and
    served on once it has finished, until the test that presses Ctrl-C (or the module's end)."""
    out = tmp_path_factory.mktemp("synthetic") / "results"
    ports = {"foxglove": free_port(), "viewer": free_port(), "router": free_port()}
    client = FoxgloveClient(ports["foxglove"], "/gridslam/map")
    client.start()
    process = start(["run", "--source", "synthetic:0", *RUN, "--listen", endpoint(ports["router"]), "--out", str(out),
                     "--foxglove", str(ports["foxglove"]), "--view", f"127.0.0.1:{ports['viewer']}"])
    run = ServedRun(out, client, process, ports)
    run.read()
    try:
        wait_for(lambda: any("serving it until Ctrl-C" in line for line in run.stdout) or process.poll() is not None,
                 timeout=300, period=0.2)
        assert process.poll() is None, "".join(run.stderr)[-3000:]
        client.halt.set()
        client.join(timeout=10)
        yield run
    finally:
        client.halt.set()
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()


@pytest.fixture(scope="module")
def synthetic_run(served_run):
    return served_run.out, served_run.client


def test_foxglove_client_receives_map_poses_during_the_run(synthetic_run):
    out, client = synthetic_run
    assert client.error is None, client.error
    assert client.advertised["encoding"] == "cdr" and client.advertised["schemaName"] == "nav_msgs/msg/Odometry"
    assert client.advertised["schemaEncoding"] == "ros2msg"
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    poses = [store.deserialize_cdr(data, "nav_msgs/msg/Odometry") for _, data in client.messages]
    # The client subscribed once the server was up, a few frames into the run at most: it got
    # the poses published before it subscribed, then every new one, each equal to the one the
    # run wrote for that frame, none twice.
    assert len(poses) == FRAMES
    reference = read_tum(out / "map_online.tum")
    by_stamp = {round(float(s) * 1e9): p for s, p in zip(reference.stamps, reference.positions)}
    for log_time, pose in zip((t for t, _ in client.messages), poses):
        stamp = pose.header.stamp.sec * 10**9 + pose.header.stamp.nanosec
        assert stamp == log_time
        assert [pose.pose.pose.position.x, pose.pose.pose.position.y] == list(by_stamp[stamp][:2])
    stamps = [t for t, _ in client.messages]
    assert stamps == sorted(set(stamps)) and stamps[-1] == max(by_stamp)


def test_the_run_says_where_it_serves_and_serves_the_finished_run(served_run):
    foxglove, viewer = f"ws://127.0.0.1:{served_run.ports['foxglove']}", f"http://127.0.0.1:{served_run.ports['viewer']}/"
    assert f"viewer: {viewer}\n" in served_run.stderr and f"foxglove: {foxglove}\n" in served_run.stderr
    assert served_run.stdout[-1] == f"the run has finished; serving it until Ctrl-C: viewer {viewer}, foxglove {foxglove}\n"
    assert any(line.startswith("results: ") for line in served_run.stdout)
    assert (served_run.out / "metrics.json").is_file() and (served_run.out / "run.mcap").is_file()
    time.sleep(1.0)
    assert served_run.process.poll() is None and port_open(served_run.ports["foxglove"]) and port_open(served_run.ports["viewer"])


def test_npm_foxglove_client_with_the_old_subprotocol_receives_every_channel_of_the_finished_run(served_run):
    """The npm @foxglove/ws-protocol client offers only foxglove.websocket.v1 (the SDK's own
    server answers that with HTTP 400); it connects after the last frame and is sent the run."""
    received = npm_foxglove.receive(f"ws://127.0.0.1:{served_run.ports['foxglove']}")
    assert received["exit_code"] == 0 and received["errors"] == [], received["errors"]
    assert received["offered"] == received["subprotocol"] == "foxglove.websocket.v1"
    assert {(c["topic"], c["schemaName"], c["encoding"], c["schemaEncoding"]) for c in received["channels"]} == {
        (topic, msgtype, "cdr", "ros2msg") for topic, msgtype in TOPICS.items()}
    recorded = read_mcap(served_run.out / "run.mcap")
    # Every channel of the run: each topic the run recorded in run.mcap came over the connection.
    assert set(received["messages"]) == set(recorded) and len(recorded) >= 10, (sorted(received["messages"]), sorted(recorded))
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    decoded = {topic: [(int(t), store.deserialize_cdr(base64.b64decode(data), TOPICS[topic])) for t, data in messages]
               for topic, messages in received["messages"].items()}
    for topic, stem in STAGE_FILES.items():   # the poses: every frame's, equal to the run's TUM files
        tum = read_tum(served_run.out / f"{stem}.tum")
        by_stamp = {round(float(s) * 1e9): p for s, p in zip(tum.stamps, tum.positions)}
        poses = decoded[topic]
        if topic != "/gridslam/groundtruth":   # the ground truth comes with newest-only camera frames
            assert len(poses) == FRAMES, topic
        assert [t for t, _ in poses] == sorted(set(t for t, _ in poses)), topic
        positions = [[pose.pose.pose.position.x, pose.pose.pose.position.y] for _, pose in poses]
        expected = [by_stamp[stamp][:2] for stamp, _ in poses]
        if topic == "/gridslam/egomotion":   # dead-reckoned again by the server: the same sums, rounded apart
            np.testing.assert_allclose(positions, expected, rtol=0, atol=1e-12)
        else:
            np.testing.assert_array_equal(positions, expected)   # the same doubles
    # The map as the run ended: the experiences of run.mcap's last MarkerArray.
    last = lambda markers: {m.ns: len(m.points) for m in markers[-1][1].markers}   # noqa: E731
    assert last(decoded["/gridslam/map/markers"])["experiences"] == last(recorded["/gridslam/map/markers"])["experiences"] >= 5


# What the viewer page shows of a run, read from its DOM.
FINISHED_PAGE = """
const rows = [...document.querySelectorAll('#health tbody tr')];
return {
  activity: document.getElementById('activity').textContent,
  activity_class: document.getElementById('activity').className,
  connection: document.getElementById('connection').textContent,
  frame: document.getElementById('frame').textContent,
  experiences: document.getElementById('experiences').textContent,
  grid: Number(document.getElementById('track-grid').dataset.count || 0),
  map: Number(document.getElementById('track-map').dataset.count || 0),
  services: Object.fromEntries(rows.map((row) => [row.children[1].textContent, [row.className, row.children[3].textContent]])),
};
"""


def test_a_browser_opening_the_viewer_after_the_run_shows_it_finished(served_run, tmp_path):
    chromium, chromedriver = chromium_and_driver()
    browser = Browser(chromium, chromedriver, tmp_path / "profile")
    try:
        browser.open(f"http://127.0.0.1:{served_run.ports['viewer']}/")   # a fresh visit, after the last frame
        page = wait_for(lambda: (p := browser.script(FINISHED_PAGE)) and p["activity"].startswith("finished") and p,
                        timeout=15, period=0.2)
        png = browser.screenshot()
        (tmp_path / "finished.png").write_bytes(png)
    finally:
        browser.close()
    assert page["activity"] == f"finished · {FRAMES} frames" and page["activity_class"] == "badge done", page
    assert page["connection"] == "live" and page["frame"] == str(FRAMES - 1), page
    assert page["grid"] >= FRAMES and page["map"] >= FRAMES and int(page["experiences"]) >= 5, page   # the final state
    # The pipeline's services stopped when the run ended; the servers still run.
    stages = ("source", "egomotion", "gridcells", "loopclosure", "expmap")
    assert {name: page["services"][name] for name in stages} == dict.fromkeys(stages, ["stopped", "stopped"]), page
    assert page["services"]["viewer"] == ["", "running"] and page["services"]["foxglove"] == ["", "running"], page
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_ctrl_c_ends_the_served_run(served_run):
    started = time.monotonic()
    served_run.process.send_signal(signal.SIGINT)
    # Alone it ends within seconds; in the whole suite it has taken longer than 20 s (not pinned
    # down: docs/reliability.md), so it gets a minute.
    code = served_run.process.wait(timeout=60)
    assert code == 0 and time.monotonic() - started < 60, "".join(served_run.stderr)[-2000:]
    assert not any(port_open(port) for port in served_run.ports.values()), served_run.ports


def test_run_mcap_has_one_odometry_per_frame_and_stage_equal_to_the_tum_files(synthetic_run):
    out, _ = synthetic_run
    messages = read_mcap(out / "run.mcap")
    for topic, stem in STAGE_FILES.items():
        tum = read_tum(out / f"{stem}.tum")
        odometry = messages[topic]
        assert len(odometry) == len(tum) == FRAMES, topic
        assert [t for t, _ in odometry] == [round(float(s) * 1e9) for s in tum.stamps]
        positions = [[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z] for _, m in odometry]
        rotations = [[m.pose.pose.orientation.x, m.pose.pose.orientation.y, m.pose.pose.orientation.z,
                      m.pose.pose.orientation.w] for _, m in odometry]
        np.testing.assert_array_equal(positions, tum.positions)   # the same doubles
        np.testing.assert_allclose(rotations, tum.quaternions, rtol=0, atol=1e-15)
    assert len(messages["/gridslam/camera/image/compressed"]) == FRAMES
    assert len(messages["/tf"]) == FRAMES and len(messages["/tf_static"]) == 1
    assert {tf.child_frame_id for _, m in messages["/tf"] for tf in m.transforms} == {
        "base_link", "gridcells_base_link", "egomotion_base_link", "groundtruth_base_link"}
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["summary"]["run_mcap"]["messages"] == sum(len(v) for v in messages.values())


def test_run_mcaps_final_map_is_map_exports_graph(synthetic_run, tmp_path):
    out, _ = synthetic_run
    gridslam(["map", "export", str(out / "experience_map.log"), "--graph", str(tmp_path / "graph.json"),
              "--tum", str(tmp_path / "map.tum")])
    graph = json.loads((tmp_path / "graph.json").read_text())
    final = {marker.ns: marker for marker in read_mcap(out / "run.mcap")["/gridslam/map/markers"][-1][1].markers}
    experiences = [(p.x, p.y) for p in final["experiences"].points]
    assert len(experiences) == len(graph["experiences"]) >= 5
    np.testing.assert_allclose(experiences, [(e["x"], e["y"]) for e in graph["experiences"]], rtol=0, atol=1e-9)
    odometric = [link for link in graph["links"] if not link["loop_closure"]]
    assert len(final["links"].points) == 2 * len(odometric)


def test_export_mcap_writes_it_again_from_the_results_folder(synthetic_run, tmp_path):
    out, _ = synthetic_run
    done = gridslam(["export", "mcap", str(out), "--out", str(tmp_path / "again.mcap")])
    assert "wrote" in done.stdout
    run, again = read_mcap(out / "run.mcap"), read_mcap(tmp_path / "again.mcap")
    for topic in [*STAGE_FILES, "/gridslam/camera/image/compressed", "/tf"]:
        assert len(again[topic]) == len(run[topic]), topic
    for topic in STAGE_FILES:
        assert [m.pose.pose.position.x for _, m in again[topic]] == [m.pose.pose.position.x for _, m in run[topic]]
    last = lambda messages: {m.ns: [(p.x, p.y) for p in m.points] for m in messages["/gridslam/map/markers"][-1][1].markers}  # noqa: E731
    np.testing.assert_allclose(last(again)["experiences"], last(run)["experiences"], rtol=0, atol=1e-9)
    assert "/gridslam/grid/activity" not in again   # not kept in a results folder


@pytest.fixture(scope="module")
def frames():
    with open_source("synthetic:0", preset="synthetic", stop=FRAMES) as source:
        return list(source)


# (storage, stereo, compression): the ROS 1 bag raw stereo, a ROS 2 sqlite3 bag of PNG mono
# frames, a ROS 2 MCAP bag of JPEG stereo frames.
BAGS = [("ros1", True, None), ("sqlite3", False, "png"), ("mcap", True, "jpeg")]


@pytest.mark.parametrize("fmt,stereo,compression", BAGS, ids=["ros1-stereo-raw", "sqlite3-mono-png", "mcap-stereo-jpeg"])
def test_a_bag_gives_the_trajectories_of_the_frames_it_holds(synthetic_run, frames, tmp_path, fmt, stereo, compression):
    reference, _ = synthetic_run
    bag = write_bag(tmp_path / ("frames.bag" if fmt == "ros1" else "frames"), frames, fmt=fmt, stereo=stereo,
                    compression=compression)
    topics = ["--image-topic", image_topic(compression=compression), "--odom-topic", ODOM]
    if stereo:
        topics += ["--right-image-topic", image_topic(compression=compression, side="right")]
    out = tmp_path / "results"
    gridslam(["run", "--source", f"rosbag:{bag}", *RUN, *topics, "--listen", endpoint(free_port()), "--out", str(out)])
    truth, truth_again = read_tum(reference / "groundtruth.tum"), read_tum(out / "groundtruth.tum")
    np.testing.assert_allclose(truth_again.positions, truth.positions, rtol=0, atol=1e-9)
    differences = {}
    for stem in COMPARED:
        ours, theirs = read_tum(out / f"{stem}.tum"), read_tum(reference / f"{stem}.tum")
        assert np.array_equal(ours.stamps, theirs.stamps), stem
        differences[stem] = float(np.abs(ours.positions - theirs.positions).max())
    if compression == "jpeg":
        # The JPEG's effect (quality 95): stated in docs/ecosystem.md from this output.
        print(f"JPEG bag vs synthetic, largest position difference per stage (m): {differences}")
        assert max(differences.values()) < 0.05
    else:
        assert differences == dict.fromkeys(COMPARED, 0.0)   # identical poses


def test_odometry_cli_reads_a_stereo_bag_like_the_synthetic_source(frames, tmp_path):
    bag = write_bag(tmp_path / "stereo.bag", frames, fmt="ros1", stereo=True)
    common = ["--preset", "synthetic", "--estimator", "stereo"]
    gridslam(["odometry", "--source", "synthetic:0", "--n-frames", str(FRAMES), *common, "--out", str(tmp_path / "a")])
    gridslam(["odometry", "--source", f"rosbag:{bag}", *common, "--image-topic", image_topic(),
              "--right-image-topic", image_topic(side="right"), "--odom-topic", ODOM, "--out", str(tmp_path / "b")])
    assert np.array_equal(read_tum(tmp_path / "a/egomotion.tum").positions, read_tum(tmp_path / "b/egomotion.tum").positions)


def test_bag_errors_are_one_line(tmp_path, frames):
    bag = write_bag(tmp_path / "mono", frames[:3], stereo=False)
    done = subprocess.run(GRIDSLAM + ["run", "--source", f"rosbag:{bag}", "--image-topic", "/nope", "--listen",
                                      endpoint(free_port()), "--out", str(tmp_path / "out")],
                          cwd=REPO, capture_output=True, text=True, timeout=60)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 1 and "no topic /nope" in lines[0], done.stderr
