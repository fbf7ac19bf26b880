"""The source service on real in-process sessions: with `wait_for` the first frame waits for
those services' health tokens; with `loop` it starts again at the first frame after the last,
seq and stamps going on, and the first frame of a new lap carries its motion from the last one;
with `resume` it starts at the last frame the running services have all handled, in its lap."""

import threading
import time

import numpy as np
import pytest
import zenoh

from schemas import CameraFrame, ServiceStatus
from services.common import codec, topics
from services.common.convert import image_from_msg, pose_to_matrix
from services.common.runtime import RuntimeConfig
from services.source.frames import planar_motion
from services.source.service import SourceConfig, SourceService
from services.source.spec import open_source
from tests.messages import header
from tests.netutil import client_session, endpoint, free_port, router_session, wait_for

FRAMES = 3


def test_source_waits_for_the_pipeline_then_loops():
    port = free_port()
    router = router_session(port)
    frames = open_source("synthetic:0", preset="synthetic", stop=FRAMES)
    config = SourceConfig(source="synthetic:0", window=0, loop=True, wait_for=["egomotion", "expmap"])
    service = SourceService(RuntimeConfig(connect=[endpoint(port)]), config, frames, instance="test")
    client = client_session(port)
    received: list[CameraFrame] = []
    lock = threading.Lock()

    def on_frame(sample: zenoh.Sample):
        with lock:
            received.append(codec.decode(sample.payload.to_bytes(), CameraFrame, str(sample.encoding)))

    subscriber = client.declare_subscriber(topics.key("robot0", "camera/frame"), on_frame)
    thread = threading.Thread(target=service.run)
    thread.start()
    tokens = []
    try:
        wait_for(lambda: service.state == "running")
        tokens.append(client.liveliness().declare_token(topics.health_key("robot0", "egomotion", "a")))
        time.sleep(1.0)   # (the source looks for the tokens every 0.2 s)
        assert not received and service.sent == 0, "a frame went out before expmap was up"
        tokens.append(client.liveliness().declare_token(topics.health_key("robot0", "expmap", "a")))
        wait_for(lambda: len(received) >= 3 * FRAMES + 1, timeout=30)
    finally:
        service.stop()
        thread.join(timeout=10)
        for token in tokens:
            token.undeclare()
        subscriber.undeclare()
        client.close()
        router.close()
    with lock:
        messages = received[:3 * FRAMES + 1]
    assert [m.header.seq for m in messages] == list(range(3 * FRAMES + 1))
    stamps = np.array([m.header.stamp.to_seconds() for m in messages])
    assert np.allclose(np.diff(stamps), 1 / 10.0)   # the synthetic world's 10 frames per second, lap after lap
    assert service.laps >= 3
    # Every lap shows the same world from the same poses; the first frame of a new lap moved from the last one.
    for lap in (1, 2):
        first = messages[lap * FRAMES]
        assert np.array_equal(image_from_msg(first.left), image_from_msg(messages[0].left))
        assert np.allclose(pose_to_matrix(first.ground_truth), pose_to_matrix(messages[0].ground_truth))
        motion = planar_motion(pose_to_matrix(messages[lap * FRAMES - 1].ground_truth), pose_to_matrix(first.ground_truth))
        assert np.allclose([first.odometry.forward, first.odometry.left, first.odometry.yaw], motion)
        assert motion[0] < -0.1   # (3 frames of a lap: the camera jumps back to its start)
    assert messages[0].odometry.forward == 0.0


def status(service: str, seq: int, received: int) -> ServiceStatus:
    return ServiceStatus(header=header(seq), service=service, instance="a", state="running", received=received,
                         published=received, decode_errors=0, gaps=0, stale=0, uptime=1.0)


@pytest.mark.parametrize("handled", [1, 7, 8, 9])
def test_resuming_source_starts_at_the_last_frame_the_services_all_handled(handled):
    """Services answer their status queries as a running pipeline does: the slowest one that has
    handled a frame decides; one restarted that has handled none does not. Laps of 3 frames:
    frame 7 is the second of lap 3, 8 its last, 9 the first of lap 4."""
    port = free_port()
    router = router_session(port)
    frames = open_source("synthetic:0", preset="synthetic", stop=FRAMES)
    config = SourceConfig(source="synthetic:0", window=0, loop=True, resume=True)
    service = SourceService(RuntimeConfig(connect=[endpoint(port)]), config, frames, instance="test")
    client = client_session(port)
    answers = [status("gridcells", handled + 2, 40), status("expmap", handled, 40), status("egomotion", 0, 0)]
    queryables = []
    for answer in answers:
        key = topics.status_key("robot0", answer.service, "a")
        queryables.append(client.declare_queryable(key, lambda query, key=key, answer=answer: query.reply(
            key, codec.encode(answer), encoding=zenoh.Encoding(codec.encoding_of(answer)))))
    received: list[CameraFrame] = []
    lock = threading.Lock()

    def on_frame(sample: zenoh.Sample):
        with lock:
            received.append(codec.decode(sample.payload.to_bytes(), CameraFrame, str(sample.encoding)))

    subscriber = client.declare_subscriber(topics.key("robot0", "camera/frame"), on_frame)
    thread = threading.Thread(target=service.run)
    thread.start()
    try:
        wait_for(lambda: len(received) >= 4, timeout=30)
    finally:
        service.stop()
        thread.join(timeout=10)
        for entity in [subscriber, *queryables]:
            entity.undeclare()
        client.close()
        router.close()
    with lock:
        messages = received[:4]
    assert [m.header.seq for m in messages] == list(range(handled, handled + 4))
    assert np.allclose([m.header.stamp.to_seconds() for m in messages], np.arange(handled, handled + 4) / 10.0)
    # Lap after lap the same world: each frame shows what frame seq mod 3 of the first lap shows.
    reference = [open_source("synthetic:0", preset="synthetic", stop=FRAMES)[i] for i in range(FRAMES)]
    for message in messages:
        assert np.array_equal(image_from_msg(message.left), reference[message.header.seq % FRAMES].left)
