"""Across machines (docs/deploy.md): routers started with deploy/router.json5 form one network.
A real gridcells service on one router is driven and read by a client of another router, which
also sees its health token; given two routers, the service moves to the second when its router
is killed. The access-controlled router config carries the same multi-machine settings."""

import json
import signal
import threading

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


def gridcells_visible(session: zenoh.Session) -> bool:
    key = topics.health_key("robot0", "gridcells", "remote")
    return any(r.ok and str(r.ok.key_expr) == key for r in session.liveliness().get(f"{topics.PREFIX}/robot0/health/**", timeout=1))


def test_routers_form_one_network_and_a_service_moves_to_its_second_router():
    a, b = free_port(), free_port()
    router_a = start_router(a)
    router_b = start_router(b, a)
    service = start_gridcells(a, b)   # on router A while it lives
    sessions = []
    try:
        # A client of router B drives and reads the service on router A, and sees its health token.
        sessions.append(client := open_session(RuntimeConfig(connect=[endpoint(b)])))
        poses = Poses(client)
        assert drive(client, poses, first=1, timeout=30)
        assert gridcells_visible(client)
        # Router A dies: the service moves to router B and the pipeline resumes.
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


def test_a_session_opens_while_its_first_router_is_down():
    down, b = free_port(), free_port()
    router_b = start_router(b)
    try:
        open_session(RuntimeConfig(connect=[endpoint(down), endpoint(b)])).close()
    finally:
        stop(router_b)
