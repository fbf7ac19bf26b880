"""The source service on real in-process sessions: with `wait_for` the first frame waits for
those services' health tokens; with `loop` it starts again at the first frame after the last,
seq and stamps going on, and the first frame of a new lap carries its motion from the last one;
with `resume` it starts at the last frame the running services have all handled, in its lap;
its adaptive window keeps a pipeline's throughput with fewer frames in flight than a fixed one."""

import multiprocessing
import queue
import threading
import time

import numpy as np
import pytest
import zenoh

from schemas import CameraFrame, MapPose, ServiceStatus
from services.common import codec, topics
from services.common.convert import image_from_msg, planar_pose, pose_to_matrix
from services.common.runtime import RuntimeConfig
from services.common.geometry import planar_motion
from services.source.service import SourceConfig, SourceService
from services.source.spec import open_source
from tests.messages import header
from tests.netutil import client_session, endpoint, free_port, router_session, wait_for

pytestmark = pytest.mark.serial   # throughput and latency of the source's window

FRAMES = 3


def subscribe_frames(client):
    """A subscriber of robot0's camera/frame, the frames it receives, and the lock to read them under."""
    received: list[CameraFrame] = []
    lock = threading.Lock()

    def on_frame(sample: zenoh.Sample):
        with lock:
            received.append(codec.decode(sample.payload.to_bytes(), CameraFrame, str(sample.encoding)))

    return client.declare_subscriber(topics.key("robot0", "camera/frame"), on_frame), received, lock


def test_source_waits_for_the_pipeline_then_loops():
    port = free_port()
    router = router_session(port)
    frames = open_source("synthetic:0", preset="synthetic", stop=FRAMES)
    config = SourceConfig(source="synthetic:0", window=0, loop=True, wait_for=["egomotion", "expmap"])
    service = SourceService(RuntimeConfig(connect=[endpoint(port)]), config, frames, instance="test")
    client = client_session(port)
    subscriber, received, lock = subscribe_frames(client)
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
    subscriber, received, lock = subscribe_frames(client)
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


def test_frames_sent_again_follow_the_last_acknowledged_ones():
    """A pipeline that acknowledges frames 0–9 and then goes quiet (a stage restarted): after
    `resend_after` the source sends the last `resend_acknowledged` acknowledged frames, oldest
    first, then the frames in flight; acknowledged, it goes on and ends."""
    port = free_port()
    router = router_session(port)
    frames = open_source("synthetic:0", preset="synthetic", stop=20)
    config = SourceConfig(source="synthetic:0", window=4, adaptive_window=False, resend_after=1.0, resend_acknowledged=5)
    service = SourceService(RuntimeConfig(connect=[endpoint(port)]), config, frames, instance="test")
    client = client_session(port)
    acknowledge = client.declare_publisher(topics.key("robot0", "map/pose"), encoding=zenoh.Encoding(codec.encoding_of(MapPose)))
    quiet = threading.Event()
    seqs: list[int] = []

    def on_frame(sample: zenoh.Sample):
        seq = codec.decode(sample.payload.to_bytes(), CameraFrame, str(sample.encoding)).header.seq
        seqs.append(seq)
        if seq < 10 or not quiet.is_set() or len(seqs) > 14:
            acknowledge.put(codec.encode(MapPose(header=header(seq, "map"), pose=planar_pose(0.0, 0.0, 0.0),
                                                 heading=0.0, experience_id=0)))
        if seq == 9:
            quiet.set()

    subscriber = client.declare_subscriber(topics.key("robot0", "camera/frame"), on_frame)
    thread = threading.Thread(target=service.run)
    thread.start()
    try:
        wait_for(lambda: not thread.is_alive(), timeout=60, period=0.1)   # every frame acknowledged in the end
    finally:
        service.stop()
        thread.join(timeout=10)
        subscriber.undeclare()
        acknowledge.undeclare()
        client.close()
        router.close()
    # 0–13 sent (10–13 in flight when the acknowledgements stopped), then 5–9 and 10–13 again, then the rest.
    assert seqs == [*range(14), *range(5, 14), *range(14, 20)]
    assert service.resent == 4


STAGES_S = (0.010, 0.030, 0.010)   # the stub pipeline: 33 frames/s, 50 ms through it when empty
REPLAY_FRAMES = 150


def stub_pipeline(port: int, stop, results) -> None:
    """Three stages in series, each a thread that takes its time from STAGES_S per frame, the last
    publishing map/pose; in a process of its own (spawned), so that the source's reading and
    encoding do not hold up the stages' threads. Puts {seq: (arrived, done)} in `results`
    (monotonic clock, shared by the processes of a machine) once `stop` is set."""
    client = client_session(port)
    queues = [queue.Queue() for _ in STAGES_S]
    arrived: dict[int, float] = {}
    done: dict[int, float] = {}
    publisher = client.declare_publisher(topics.key("robot0", "map/pose"), encoding=zenoh.Encoding(codec.encoding_of(MapPose)))

    def on_frame(sample: zenoh.Sample):
        seq = codec.decode(sample.payload.to_bytes(), CameraFrame, str(sample.encoding)).header.seq
        arrived.setdefault(seq, time.monotonic())
        queues[0].put(seq)

    def stage(index: int):
        while (seq := queues[index].get()) is not None:
            time.sleep(STAGES_S[index])
            if index + 1 < len(STAGES_S):
                queues[index + 1].put(seq)
            elif seq not in done:
                done[seq] = time.monotonic()
                publisher.put(codec.encode(MapPose(header=header(seq, "map"), pose=planar_pose(0.0, 0.0, 0.0),
                                                   heading=0.0, experience_id=0)))

    workers = [threading.Thread(target=stage, args=(index,)) for index in range(len(STAGES_S))]
    for worker in workers:
        worker.start()
    subscriber = client.declare_subscriber(topics.key("robot0", "camera/frame"), on_frame)
    stop.wait(120)
    subscriber.undeclare()
    for q in queues:
        q.put(None)
    for worker in workers:
        worker.join(timeout=10)
    publisher.undeclare()
    client.close()
    results.put({seq: (arrived[seq], at) for seq, at in done.items()})


def replay_through_stub_stages(adaptive: bool) -> tuple[float, float, float, int]:
    """A replaying source (window 8) and the stub pipeline on real sessions: (frames/s, p50 and
    p99 frame→map/pose latency in ms as the stages see them, the source's last window)."""
    port = free_port()
    router = router_session(port)
    frames = open_source("synthetic:0", preset="synthetic", stop=REPLAY_FRAMES)
    config = SourceConfig(source="synthetic:0", window=8, adaptive_window=adaptive)
    service = SourceService(RuntimeConfig(connect=[endpoint(port)]), config, frames, instance="test")
    spawn = multiprocessing.get_context("spawn")
    stop, results = spawn.Event(), spawn.Queue()
    stub = spawn.Process(target=stub_pipeline, args=(port, stop, results))
    stub.start()
    thread = threading.Thread(target=service.run)
    thread.start()
    try:
        wait_for(lambda: not thread.is_alive(), timeout=60, period=0.1)   # it exits once every frame is acknowledged
    finally:
        service.stop()
        thread.join(timeout=10)
        stop.set()
        times = results.get(timeout=30)
        stub.join(timeout=10)
        router.close()
    assert sorted(times) == list(range(REPLAY_FRAMES))
    latencies = np.array([done - arrived for arrived, done in times.values()]) * 1e3
    finished = sorted(done for _, done in times.values())
    return ((len(finished) - 1) / (finished[-1] - finished[0]), float(np.percentile(latencies, 50)),
            float(np.percentile(latencies, 99)), service.limit)


def test_adaptive_window_keeps_the_throughput_of_a_fixed_window_at_a_fraction_of_its_latency():
    """Replay through stub stages of 10, 30 and 10 ms (sleeps in a process of their own, so the
    measure hardly depends on the machine's load): the adaptive window (at most 8) keeps the 30 ms stage as busy as a fixed
    window of 8 does with about 4 frames in flight (2 keep it busy, and the margin's 2), so a frame
    waits in queues for about half as long."""
    fixed = replay_through_stub_stages(adaptive=False)
    adaptive = replay_through_stub_stages(adaptive=True)
    print(f"fixed window of 8: {fixed[0]:.1f} frames/s, p50 {fixed[1]:.0f} ms, p99 {fixed[2]:.0f} ms; "
          f"adaptive: {adaptive[0]:.1f} frames/s, p50 {adaptive[1]:.0f} ms, p99 {adaptive[2]:.0f} ms, window {adaptive[3]}")
    assert fixed[3] == 8 and 3 <= adaptive[3] <= 5
    assert adaptive[0] >= 0.9 * fixed[0]
    assert adaptive[1] <= 0.65 * fixed[1]
