"""Process level: `gridslam router` and `gridslam service gridcells` as real subprocesses.
The health token appears, garbage on the input key is counted while the service stays up,
`gridslam health` shows the counters, and SIGTERM ends the service in under 2 s with exit 0."""

import signal
import time

import msgpack

from services.common import codec, topics
from tests.netutil import client_session, endpoint, free_port, start, start_router, stop, wait_for


def status_of(session, service: str):
    for reply in session.get(f"{topics.PREFIX}/robot0/status/{service}/**", timeout=1):
        if reply.ok:
            return codec.decode(reply.ok.payload.to_bytes(), encoding=str(reply.ok.encoding))
    return None


def test_service_survives_garbage_and_stops_on_sigterm():
    port = free_port()
    router = start_router(port)
    service = start(["service", "gridcells", "--integrator", "deadreckoning", "-e", endpoint(port), "--instance", "e2e"])
    session = client_session(port)
    try:
        health = f"{topics.PREFIX}/robot0/health/gridcells/e2e"
        wait_for(lambda: any(r.ok and str(r.ok.key_expr) == health
                             for r in session.liveliness().get(f"{topics.PREFIX}/robot0/health/**", timeout=1)))
        key = topics.key("robot0", "egomotion")
        garbage = [b"\x00\xff garbage", msgpack.packb({"header": 1}), msgpack.packb([1, 2]), b""]
        for payload in garbage:
            session.put(key, payload, encoding="application/msgpack;EgoMotion")
        session.put(key, msgpack.packb({"x": 1}), encoding="application/msgpack;GridPose")   # wrong kind
        status = wait_for(lambda: (s := status_of(session, "gridcells")) and s.decode_errors >= 5 and s)
        assert status.decode_errors == 5 and status.received == 0 and service.poll() is None

        listing = start(["health", "-e", endpoint(port)])
        out, err = listing.communicate(timeout=15)
        code = listing.returncode
        assert code == 0, err
        row = next(line for line in out.splitlines() if " gridcells " in f" {line} ")
        assert row.split()[:4] == ["robot0", "gridcells", "e2e", "running"] and row.split()[6] == "5"

        started = time.monotonic()
        service.send_signal(signal.SIGTERM)
        code = service.wait(timeout=5)
        assert code == 0 and time.monotonic() - started < 2.0
        wait_for(lambda: not any(r.ok for r in session.liveliness().get(health, timeout=1)))
    finally:
        session.close()
        stop(service)
        stop(router)
