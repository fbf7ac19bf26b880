"""run.mcap's writer on made-up content: every message is read back with the `mcap` reader and
decoded by mcap-ros2-support (an implementation independent of the encoder that wrote it)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from tests.extras import require

require("rosbags", "ros")
require("mcap_ros2", "test")

from mcap.reader import make_reader   # noqa: E402
from mcap_ros2.decoder import DecoderFactory   # noqa: E402

from services.evaluation.trajectory import Trajectory   # noqa: E402
from services.ros.mcap_export import MARKER_PERIOD_S, RunContent, write_run_mcap   # noqa: E402
from services.common.observe import CLOSURE_KEPT, CLOSURE_REFUSED, ODOMETRIC   # noqa: E402
from services.ros2wire.messages import STAGES, TOPICS, MapState   # noqa: E402

FRAMES = 30
FPS = 10.0


def read(path):
    """(summary, [(topic, log_time, schema, decoded message)]) of an MCAP file."""
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        header, summary = reader.get_header(), reader.get_summary()
        messages = [(channel.topic, message.log_time, schema, decoded)
                    for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False)]
    return header, summary, messages


def content() -> RunContent:
    stamps = 1000.0 + np.arange(FRAMES) / FPS   # absolute stamps, as a bag's
    trajectories = {}
    for offset, stage in enumerate(STAGES):
        heading = 0.05 * np.arange(FRAMES) + 0.01 * offset
        trajectories[stage] = Trajectory.from_planar(stamps, np.cos(heading) * (3 + offset), np.sin(heading) * 3, heading)
    image = np.tile(np.arange(64, dtype=np.uint8), (48, 1))
    jpeg = cv2.imencode(".jpg", image)[1].tobytes()
    updates = [(stamps[i], [(i, float(i), 0.5 * i)], [(i - 1, i, ODOMETRIC)] if i else []) for i in range(FRAMES)]
    updates[20] = (stamps[20], [(20, 20.0, 10.0)], [(19, 20, ODOMETRIC), (20, 2, CLOSURE_KEPT), (20, 5, CLOSURE_REFUSED)])
    return RunContent(
        trajectories=trajectories,
        images=[(stamp, jpeg) for stamp in stamps],
        camera_model=(50.0, 50.0, 32.0, 24.0, 64, 48),
        lattices=[(stamps[i], np.full((8, 8), i, np.uint8)) for i in range(0, FRAMES, 5)],
        map_updates=updates,
        closures=[(stamps[20], {"frame": 20, "matched_frame": 2, "matched_template": 1, "votes": 7})],
        metadata={"source": "test"},
    )


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    path = tmp_path_factory.mktemp("mcap") / "run.mcap"
    made = content()
    counts = write_run_mcap(path, made)
    return made, counts, read(path)


def test_every_message_is_ros2_cdr_in_stamp_order(written):
    made, counts, (header, summary, messages) = written
    assert header.profile == "ros2"
    assert {schema.encoding for schema in summary.schemas.values()} == {"ros2msg"}
    assert {channel.message_encoding for channel in summary.channels.values()} == {"cdr"}
    times = [log_time for _, log_time, _, _ in messages]
    assert times == sorted(times)   # written in stamp order: a player needs no reordering
    for topic, log_time, _, message in messages:
        if hasattr(message, "header"):
            assert message.header.stamp.sec * 10**9 + message.header.stamp.nanosec == log_time, topic
    per_topic = {topic: sum(1 for t, *_ in messages if t == topic) for topic in counts}
    assert per_topic == counts
    assert counts["/tf"] == FRAMES and counts["/tf_static"] == 1   # one per stamp, every stage's transform in it
    assert counts["/gridslam/camera/image/compressed"] == counts["/gridslam/camera/camera_info"] == FRAMES
    assert counts["/gridslam/grid/activity"] == 6 and counts["/gridslam/loop_closure"] == 1


def test_one_odometry_per_frame_and_stage_equal_to_its_trajectory(written):
    made, counts, (_, _, messages) = written
    for stage, (topic, body) in STAGES.items():
        odometry = [m for t, _, _, m in messages if t == topic]
        trajectory = made.trajectories[stage]
        assert len(odometry) == FRAMES and all(m.header.frame_id == "map" and m.child_frame_id == body for m in odometry)
        positions = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z] for m in odometry])
        rotations = np.array([[q.x, q.y, q.z, q.w] for q in (m.pose.pose.orientation for m in odometry)])
        assert np.array_equal(positions, trajectory.positions) and np.array_equal(rotations, trajectory.quaternions)
        transforms = [tf for t, _, _, m in messages if t == "/tf" for tf in m.transforms if tf.child_frame_id == body]
        assert [tf.transform.translation.x for tf in transforms] == list(trajectory.positions[:, 0])


def test_the_map_markers_follow_the_map_and_end_with_it(written):
    made, counts, (_, _, messages) = written
    arrays = [(log_time, m) for t, log_time, _, m in messages if t == "/gridslam/map/markers"]
    # The map changes every frame (3 s at 10 Hz): at most one array per MARKER_PERIOD_S, plus the end.
    assert 3 <= len(arrays) <= 3 / MARKER_PERIOD_S + 2
    final = {marker.ns: marker for marker in arrays[-1][1].markers}
    state = MapState()
    for _, experiences, links in made.map_updates:
        state.apply(experiences, links)
    points = [(p.x, p.y) for p in final["experiences"].points]
    assert points == [state.experiences[i] for i in sorted(state.experiences)]   # in id order
    assert final["experiences"].type == 7 and final["links"].type == 5
    assert len(final["links"].points) == 2 * (FRAMES - 1)
    assert [(p.x, p.y) for p in final["closures"].points] == [(20.0, 10.0), (2.0, 1.0)]
    assert [(p.x, p.y) for p in final["closures_refused"].points] == [(20.0, 10.0), (5.0, 2.5)]
    assert final["closures"].color.r > 0.8 and final["closures_refused"].color.r < 0.6


def test_images_camera_info_lattices_and_closures(written):
    made, counts, (_, _, messages) = written
    first = lambda topic: next(m for t, _, _, m in messages if t == topic)   # noqa: E731
    image = first("/gridslam/camera/image/compressed")
    assert image.format == "jpeg" and image.header.frame_id == "camera"
    assert cv2.imdecode(np.frombuffer(bytes(image.data), np.uint8), cv2.IMREAD_GRAYSCALE).shape == (48, 64)
    info = first("/gridslam/camera/camera_info")
    assert (info.width, info.height) == (64, 48) and list(info.k) == [50, 0, 32, 0, 50, 24, 0, 0, 1]
    infos = [(log_time, m) for t, log_time, _, m in messages if t == "/gridslam/camera/camera_info"]
    assert all(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == log_time for log_time, m in infos)   # restamped
    lattice = first("/gridslam/grid/activity")
    assert (lattice.encoding, lattice.width, lattice.height) == ("mono8", 8, 8) and set(bytes(lattice.data)) == {0}
    assert json.loads(first("/gridslam/loop_closure").data) == {"frame": 20, "matched_frame": 2, "matched_template": 1,
                                                              "votes": 7}
    static = first("/tf_static").transforms[0]
    assert (static.header.frame_id, static.child_frame_id) == ("base_link", "camera")
    q = static.transform.rotation
    # The optical frame's axes in the body frame: z (forward) is the body's x, x (right) its −y.
    z_axis = [2 * (q.x * q.z + q.w * q.y), 2 * (q.y * q.z - q.w * q.x), 1 - 2 * (q.x**2 + q.y**2)]
    x_axis = [1 - 2 * (q.y**2 + q.z**2), 2 * (q.x * q.y + q.w * q.z), 2 * (q.x * q.z - q.w * q.y)]
    assert z_axis == pytest.approx([1, 0, 0]) and x_axis == pytest.approx([0, -1, 0])


def test_map_state_counts_a_change_only_when_there_is_one():
    state = MapState()
    assert state.apply([(0, 0.0, 0.0), (1, 1.0, 0.0)], [(0, 1, ODOMETRIC)])
    assert not state.apply([(1, 1.0, 0.0)], [(0, 1, ODOMETRIC)])
    assert state.apply([(1, 1.0, 0.1)], [])
    assert state.apply([], [(1, 0, CLOSURE_REFUSED)]) and state.links[(1, 0)] == CLOSURE_REFUSED


def test_a_run_without_the_extra_writes_no_mcap_and_says_so(monkeypatch, tmp_path, caplog):
    from types import SimpleNamespace

    from services.pipeline.recorder import Recording
    from services.ros import mcap_export
    from services.ros2wire.messages import RosUnavailable

    def unavailable(*args, **kwargs):
        raise RosUnavailable("ROS messages need the optional extra 'ros': pip install 'gridslam[ros]'")

    monkeypatch.setattr(mcap_export, "write_run_mcap", unavailable)
    config = SimpleNamespace(source="synthetic:0", robot="robot0", preset=None)
    assert mcap_export.write_after_run(tmp_path, Recording(), {}, config) is None
    assert "pip install 'gridslam[ros]'; no run.mcap written" in caplog.text
    assert not (tmp_path / "run.mcap").exists()


def test_the_foxglove_server_binds_loopback_unless_allowed():
    from pydantic import ValidationError

    from services.ros.foxglove import FoxgloveConfig

    assert FoxgloveConfig().host == "127.0.0.1" and FoxgloveConfig().port == 8765
    with pytest.raises(ValidationError, match="needs --allow-remote"):
        FoxgloveConfig(host="0.0.0.0")
    assert FoxgloveConfig(host="0.0.0.0", allow_remote=True).host == "0.0.0.0"


def test_the_foxglove_server_says_in_one_line_that_its_port_is_taken():
    require("foxglove", "foxglove")
    import socket

    from services.common.errors import ConfigError
    from services.common.runtime import RuntimeConfig
    from services.ros.foxglove import FoxgloveConfig, FoxgloveService

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ConfigError, match=rf"foxglove: cannot serve on 127.0.0.1:{port}: .*in use"):
            FoxgloveService(RuntimeConfig(), FoxgloveConfig(port=port))
    service = FoxgloveService(RuntimeConfig(), FoxgloveConfig(port=0))   # any free port
    try:
        assert service.url == f"ws://127.0.0.1:{service.relay.port}" and service.relay.port > 0
        assert set(service.msgdefs) == set(TOPICS.values())   # each client's channels: every topic's type
    finally:
        service.close_server()


def test_every_channel_offers_its_qos_and_tf_static_is_latched(tmp_path):
    # The MCAP ros2 profile's offered_qos_profiles, read back as `ros2 bag play` would: without
    # it /tf_static is replayed volatile and static-transform listeners never get it.
    path = tmp_path / "run.mcap"
    write_run_mcap(path, content())
    with open(path, "rb") as stream:
        channels = make_reader(stream).get_summary().channels.values()
    profiles = {channel.topic: channel.metadata.get("offered_qos_profiles", "") for channel in channels}
    assert profiles and all(profile.startswith("- history: 3\n") for profile in profiles.values()), profiles
    durability = {topic: [line for line in profile.splitlines() if "durability" in line][0].split(":")[1].strip()
                  for topic, profile in profiles.items()}
    assert durability.pop("/tf_static") == "1"                       # TRANSIENT_LOCAL
    assert set(durability.values()) == {"2"}                          # VOLATILE
