"""Swap: the ego-motion estimator is replaced by another process mid-run while the others keep
running; the source re-sends the frames that were in flight, and no frame is lost."""

import signal
import threading

import zenoh

from services.common import codec, topics
from tests.netutil import client_session, endpoint, free_port, start, start_router, stop, wait_for

FRAMES = 60


def test_swap_the_estimator_without_restarting_the_others():
    port = free_port()
    router = start_router(port)
    connect = ["-e", endpoint(port)]
    gridcells = start(["service", "gridcells", "--integrator", "deadreckoning", "--instance", "gc", *connect])
    first = start(["service", "egomotion", "--estimator", "passthrough", "--instance", "first", *connect])
    session = client_session(port)
    estimators: dict[int, str] = {}
    poses: set[int] = set()
    lock = threading.Lock()

    def on_egomotion(sample: zenoh.Sample) -> None:
        message = codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding))
        with lock:
            estimators.setdefault(message.header.seq, message.estimator)

    def on_pose(sample: zenoh.Sample) -> None:
        with lock:
            poses.add(codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding)).header.seq)

    subscribers = [session.declare_subscriber(topics.key("robot0", "egomotion"), on_egomotion),
                   session.declare_subscriber(topics.key("robot0", "grid/pose"), on_pose)]
    second = source = None
    try:
        live = lambda name: any(r.ok for r in session.liveliness().get(  # noqa: E731
            f"{topics.PREFIX}/robot0/health/{name}", timeout=1))
        wait_for(lambda: live("gridcells/gc") and live("egomotion/first"), timeout=60)
        source = start(["service", "source", "--source", "synthetic:0", "--preset", "synthetic", "--stop", str(FRAMES),
                        "--rate", "20", "--window", "4", "--ack-topic", "grid/pose", "--resend-after", "1", *connect])
        wait_for(lambda: len(poses) >= 20, timeout=60)
        first.send_signal(signal.SIGTERM)
        assert first.wait(timeout=5) == 0
        second = start(["service", "egomotion", "--estimator", "stereo", "--preset", "synthetic", "--instance", "second",
                        *connect])
        assert source.wait(timeout=120) == 0, source.communicate()[1]
        with lock:
            assert poses == set(range(FRAMES))
            names = [estimators[seq] for seq in range(FRAMES)]
        # The first estimator served the start, the second the end, each frame exactly once.
        switch = names.index("stereo")
        assert 20 <= switch < FRAMES and names[:switch] == ["passthrough"] * switch
        assert names[switch:] == ["stereo"] * (FRAMES - switch)
        assert gridcells.poll() is None, "gridcells was restarted or died"
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
        session.close()
        for process in (source, second, first, gridcells):
            if process is not None:
                stop(process)
        stop(router)
