"""Across machines (docs/deploy.md): routers started with deploy/router.json5 form one network.
A real gridcells service on one router is driven and read from another router's clients, and
`gridslam health` on either sees it; a service given two routers moves to the second when its
router is killed. The access-controlled router config carries the same multi-machine settings."""

import json
import signal
import threading

import pytest
import zenoh

from services.common import codec, topics
from services.common.runtime import RuntimeConfig, open_session
from tests.messages import sample_messages
from tests.netutil import REPO, endpoint, free_port, port_open, start, stop, wait_for

ROUTER_CONFIG = REPO / "deploy" / "router.json5"
ACL_ROUTER_CONFIG = REPO / "deploy" / "acl" / "router.json5"


def test_access_controlled_router_has_the_multi_machine_settings():
    parsed = {path: json.loads(str(zenoh.Config.from_file(str(path)))) for path in (ROUTER_CONFIG, ACL_ROUTER_CONFIG)}
    plain, secure = parsed[ROUTER_CONFIG], parsed[ACL_ROUTER_CONFIG]
    assert plain["scouting"] == secure["scouting"]
    assert plain["connect"] == secure["connect"]
    assert plain["transport"]["link"]["tx"] == secure["transport"]["link"]["tx"]
    assert plain["scouting"]["multicast"]["enabled"] is False


def start_router(port: int, *peers: int):
    """`gridslam router` with deploy/router.json5, connecting to `peers` through the environment
    (as docker-compose.yml's GRIDSLAM_PEER_ROUTERS does)."""
    env = {"GRIDSLAM_RUNTIME_CONNECT": ",".join(endpoint(peer) for peer in peers)}
    router = start(["router", "--zenoh-config", str(ROUTER_CONFIG), "--listen", endpoint(port)], env=env)
    wait_for(lambda: port_open(port) or router.poll() is not None)
    assert router.poll() is None, router.communicate()[1]
    return router


def start_gridcells(*ports: int):
    env = {"GRIDSLAM_RUNTIME_CONNECT": ",".join(endpoint(port) for port in ports), "GRIDSLAM_GRIDCELLS_INTEGRATOR": "deadreckoning"}
    return start(["service", "gridcells", "--instance", "remote"], env=env)


class Poses:
    def __init__(self, session: zenoh.Session):
        self.seqs: list[int] = []
        self._lock = threading.Lock()
        self._subscriber = session.declare_subscriber(topics.key("robot0", "grid/pose"), self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.seqs.append(codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding)).header.seq)

    def since(self, first: int) -> list[int]:
        with self._lock:
            return [seq for seq in self.seqs if seq >= first]


def drive(session: zenoh.Session, poses: Poses, first: int, timeout: float = 15) -> list[int]:
    """Publish EgoMotion from frame `first` on until grid/pose answers; returns the answered frames."""
    frames = iter(range(first, first + 100000))

    def answered():
        message = next(m for m in sample_messages(next(frames)) if m.KIND == "EgoMotion")
        session.put(topics.key("robot0", "egomotion"), codec.encode(message), encoding=zenoh.Encoding(codec.encoding_of(message)))
        return poses.since(first)
    return wait_for(answered, timeout=timeout, period=0.1)


def health_rows(port: int) -> list[list[str]]:
    listing = start(["health", "--timeout", "1", "-e", endpoint(port)])
    out, err = listing.communicate(timeout=30)
    assert listing.returncode == 0, err
    return [line.split() for line in out.splitlines() if " gridcells " in f" {line} "]


def test_a_service_on_one_router_serves_clients_of_another():
    a, b = free_port(), free_port()
    router_a = start_router(a)
    router_b = start_router(b, a)
    service = start_gridcells(b)
    sessions = []
    try:
        sessions.append(client := open_session(RuntimeConfig(connect=[endpoint(a)])))
        poses = Poses(client)
        assert drive(client, poses, first=1, timeout=30)
        assert health_rows(a)[0][:3] == ["robot0", "gridcells", "remote"]
        assert service.poll() is None
    finally:
        for session in sessions:
            session.close()
        code, _, err = stop(service)
        stop(router_b)
        stop(router_a)
    assert code == 0, err


def test_a_service_moves_to_its_second_router_when_the_first_dies():
    a, b = free_port(), free_port()
    router_a = start_router(a)
    router_b = start_router(b, a)
    service = start_gridcells(a, b)
    sessions = []
    try:
        sessions.append(client := open_session(RuntimeConfig(connect=[endpoint(b)])))
        poses = Poses(client)
        assert drive(client, poses, first=1, timeout=30)
        router_a.send_signal(signal.SIGKILL)
        router_a.wait(timeout=5)
        assert drive(client, poses, first=1000, timeout=15)
        assert service.poll() is None
    finally:
        for session in sessions:
            session.close()
        code, _, err = stop(service)
        stop(router_b)
        stop(router_a)
    assert code == 0, err


@pytest.mark.xfail(strict=True, reason=(
    "services/common/runtime.py sets connect/timeout_ms=1000 for clients: Zenoh then retries the first endpoint "
    "until the timeout and never tries the next, so a service whose first router is down never opens. With "
    "timeout_ms 0 (one try per endpoint; open_session's loop retries) it opens on the second. Remove this marker then."))
def test_a_service_starts_while_its_first_router_is_down():
    down, b = free_port(), free_port()
    router_b = start_router(b)
    service = start_gridcells(down, b)
    sessions = []
    try:
        sessions.append(client := open_session(RuntimeConfig(connect=[endpoint(b)])))
        poses = Poses(client)
        assert drive(client, poses, first=1, timeout=5)
    finally:
        for session in sessions:
            session.close()
        stop(service)
        stop(router_b)
