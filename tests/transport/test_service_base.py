"""The service base on real in-process sessions: a message the core rejects is counted and the
service keeps running; gaps and stale seq numbers are counted; a re-sent frame gets the outputs
published for it the first time; messages published out of order by several instances are
handled in the order their `previous_seq` links give; a stop ends the loop and closes the session;
frames published while the router was away are recovered by Zenoh's advanced publisher and
subscriber and handled in order."""

import threading
import time

import pytest
import zenoh

from schemas import EgoMotion, GridPose, PlanarIncrement
from services.common import codec, topics
from services.common.errors import DataError
from services.common.runtime import RuntimeConfig
from services.common import service as service_base
from services.common.service import Service
from services.common.convert import planar_pose
from tests.messages import header
from tests.netutil import client_session, endpoint, free_port, router_session, wait_for


class Doubler(Service):
    """Publishes a grid/pose at x = 2·forward for every egomotion; rejects a negative forward."""

    name = "doubler"

    def __init__(self, runtime, in_order: bool = False):
        super().__init__(runtime, instance="test")
        self.handled: list[int] = []
        self.in_order = in_order

    def setup(self):
        self.subscribe("egomotion", self.on_egomotion,
                       follows=(lambda message: message.previous_seq) if self.in_order else None)

    def on_egomotion(self, message: EgoMotion):
        if message.increment.forward < 0:
            raise DataError("negative forward")
        self.handled.append(message.header.seq)
        self.publish("grid/pose", GridPose(header=message.header, pose=planar_pose(2 * message.increment.forward, 0, 0),
                                           heading=0.0, lattice_shift=(0.0, 0.0), step_length=0.0, integrator="grid"))


def egomotion(seq: int, forward: float, previous: int | None = None) -> bytes:
    return codec.encode(EgoMotion(header=header(seq), previous_seq=previous, quality=1.0, estimator="passthrough",
                                  increment=PlanarIncrement(forward=forward, left=0.0, yaw=0.0)))


@pytest.fixture
def in_order_service(monkeypatch):
    """A Doubler that puts messages in order by previous_seq, on a router; yields (service, publisher)."""
    monkeypatch.setattr(service_base, "ORDER_WAIT_S", 1.0)
    port = free_port()
    router = router_session(port)
    service = Doubler(RuntimeConfig(connect=[endpoint(port)]), in_order=True)
    thread = threading.Thread(target=service.run)
    thread.start()
    client = client_session(port)
    try:
        wait_for(lambda: any(r.ok for r in client.liveliness().get(topics.health_key("robot0", "doubler", "test"), timeout=1)))
        yield service, client.declare_publisher(topics.key("robot0", "egomotion"),
                                                encoding=zenoh.Encoding(codec.encoding_of(EgoMotion)))
    finally:
        service.stop()
        thread.join(timeout=5)
        client.close()
        router.close()


def test_messages_wait_for_the_one_they_follow(in_order_service):
    service, publisher = in_order_service
    # Two instances' blocks arrive interleaved; 2 twice; 7 follows 5 (6 was never a frame).
    for seq, previous in ((0, None), (3, 2), (4, 3), (1, 0), (2, 1), (2, 1), (7, 5), (5, 4)):
        publisher.put(egomotion(seq, 1.0, previous))
    wait_for(lambda: len(service.handled) >= 7)
    assert service.handled == [0, 1, 2, 3, 4, 5, 7]
    c = service.counters
    assert (c.stale, c.gaps) == (1, 1)


def test_a_message_whose_predecessor_never_comes_waits_a_bounded_time(in_order_service):
    service, publisher = in_order_service
    publisher.put(egomotion(0, 1.0, None))
    publisher.put(egomotion(2, 1.0, 1))   # 1 was lost for good
    publisher.put(egomotion(3, 1.0, 2))
    wait_for(lambda: service.handled == [0])
    wait_for(lambda: service.handled == [0, 2, 3], timeout=5)   # after ORDER_WAIT_S (1 s here)
    assert service.counters.gaps == 1


def test_rejections_gaps_stale_and_replay():
    port = free_port()
    router = router_session(port)
    service = Doubler(RuntimeConfig(connect=[endpoint(port)]))
    thread = threading.Thread(target=service.run)
    thread.start()
    client = client_session(port)
    poses: list[tuple[int, float]] = []
    lock = threading.Lock()

    def on_pose(sample: zenoh.Sample):
        message = codec.decode(sample.payload.to_bytes(), GridPose, str(sample.encoding))
        with lock:
            poses.append((message.header.seq, message.pose.position.x))

    subscriber = client.declare_subscriber(topics.key("robot0", "grid/pose"), on_pose)
    try:
        wait_for(lambda: any(r.ok for r in client.liveliness().get(topics.health_key("robot0", "doubler", "test"), timeout=1)))
        publisher = client.declare_publisher(topics.key("robot0", "egomotion"),
                                             encoding=zenoh.Encoding(codec.encoding_of(EgoMotion)))
        # seq 0, a rejected 1, a gap before 4, then 0 again (stale: its output is replayed, not recomputed).
        for seq, forward in ((0, 1.0), (1, -1.0), (4, 3.0), (0, 5.0)):
            publisher.put(egomotion(seq, forward))
        wait_for(lambda: len(poses) == 3)
        with lock:
            assert poses == [(0, 2.0), (4, 6.0), (0, 2.0)]
        assert service.handled == [0, 4]
        c = service.counters
        assert (c.received, c.rejected, c.gaps, c.stale, c.replayed) == (4, 1, 2, 1, 1)
        assert thread.is_alive()
        extra = service.status().extra
        assert {name: extra[name] for name in ("replayed", "rejected")} == {"replayed": 1, "rejected": 1}
        assert set(extra) == {"replayed", "rejected", "cpu_s", "serving_cpu_s", "busy_cpu_s"}
        assert 0 <= extra["busy_cpu_s"] <= extra["serving_cpu_s"] <= extra["cpu_s"]
    finally:
        service.stop()
        thread.join(timeout=5)
        subscriber.undeclare()
        client.close()
        router.close()
    assert not thread.is_alive() and service.session is None


@pytest.mark.parametrize("recovered, after", [(True, 10), (True, 0), (False, 10)])
def test_frames_published_while_the_router_was_away_are_recovered_in_order(monkeypatch, recovered, after):
    """The router dies after frame 49 of egomotion and comes back on its port 1 s later; frames
    50-99 are published while it is away, then `after` more. The pipeline's publisher (numbered,
    cached) and the service's subscriber recover them, and the service handles every frame once,
    in order; with none after them, the subscriber's periodic query finds them. With plain
    publishers and subscribers (recovers() false) those frames are lost: what the test sees is
    the recovery's doing."""
    if not recovered:
        monkeypatch.setattr(service_base, "recovers", lambda topic: False)
    port = free_port()
    router = router_session(port)
    service = Doubler(RuntimeConfig(connect=[endpoint(port)]))
    thread = threading.Thread(target=service.run)
    thread.start()
    client = client_session(port)
    try:
        wait_for(lambda: any(r.ok for r in client.liveliness().get(topics.health_key("robot0", "doubler", "test"), timeout=1)))
        publisher = service_base.declare_publisher(client, "robot0", "egomotion")
        time.sleep(0.5)   # (the subscriber has met the publisher)
        for seq in range(50):
            publisher.put(egomotion(seq, 1.0))
        wait_for(lambda: len(service.handled) == 50)
        router.close()
        for seq in range(50, 100):
            publisher.put(egomotion(seq, 1.0))
        time.sleep(1.0)
        router = router_session(port)
        wait_for(lambda: service.state == "running" and not service._link.down, timeout=10)
        time.sleep(0.5)   # (the client has its link back too)
        for seq in range(100, 100 + after):   # (within the cache's CACHE_SAMPLES of the ones lost)
            publisher.put(egomotion(seq, 1.0))
        wait_for(lambda: service.handled and service.handled[-1] == 99 + after, timeout=10)
    finally:
        service.stop()
        thread.join(timeout=5)
        client.close()
        router.close()
    if recovered:
        assert service.handled == list(range(100 + after)) and service.counters.gaps == 0
    else:
        assert service.handled == sorted(set(service.handled)) and service.counters.gaps >= 40
