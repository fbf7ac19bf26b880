"""The service base on real in-process sessions: a message the core rejects is counted and the
service keeps running; gaps and stale seq numbers are counted; a re-sent frame gets the outputs
published for it the first time; a stop ends the loop and closes the session."""

import threading

import zenoh

from schemas import EgoMotion, GridPose, PlanarIncrement
from services.common import codec, topics
from services.common.errors import DataError
from services.common.runtime import RuntimeConfig
from services.common.service import Service
from services.common.convert import planar_pose
from tests.messages import header
from tests.netutil import client_session, endpoint, free_port, router_session, wait_for


class Doubler(Service):
    """Publishes a grid/pose at x = 2·forward for every egomotion; rejects a negative forward."""

    name = "doubler"

    def __init__(self, runtime):
        super().__init__(runtime, instance="test")
        self.handled: list[int] = []

    def setup(self):
        self.subscribe("egomotion", self.on_egomotion)

    def on_egomotion(self, message: EgoMotion):
        if message.increment.forward < 0:
            raise DataError("negative forward")
        self.handled.append(message.header.seq)
        self.publish("grid/pose", GridPose(header=message.header, pose=planar_pose(2 * message.increment.forward, 0, 0),
                                           heading=0.0, lattice_shift=(0.0, 0.0), step_length=0.0, integrator="grid"))


def egomotion(seq: int, forward: float) -> bytes:
    return codec.encode(EgoMotion(header=header(seq), increment=PlanarIncrement(forward=forward, left=0.0, yaw=0.0),
                                  quality=1.0, estimator="passthrough"))


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
        assert service.status().extra == {"replayed": 1, "rejected": 1}
    finally:
        service.stop()
        thread.join(timeout=5)
        subscriber.undeclare()
        client.close()
        router.close()
    assert not thread.is_alive() and service.session is None
