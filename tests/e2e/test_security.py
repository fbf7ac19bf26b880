"""Security with the real command line: `gridslam router` with the shipped access-controlled
mutual-TLS config (deploy/acl/router.json5) and a real `gridslam service gridcells` holding
the gridcells certificate, every certificate made by deploy/make-certs.sh into the test's
folder.

- An authorised publisher (the egomotion certificate) on the pipeline key `egomotion` drives
  gridcells; the same publication from an outside client (the observer certificate) is not
  delivered, and the observer cannot read that key either, while it does receive `grid/pose`.
- `gridslam health` with the operator certificate lists the service and its counters (the
  status query and its reply pass); the observer certificate sees neither; without a client
  certificate `gridslam health` cannot connect at all.
- A fleet (docs/fleet.md): two real `gridslam service loopclosure --fleet` (robots a and b, the
  loopclosure certificate) fed stereo frames learn each other's places, and a real `gridslam
  service fleetmap` (the fleetmap certificate) takes robot a's map from an expmap and publishes
  its fleet pose, which an outside client may read; places, fleet poses and map updates put by
  certificates without those rights are not delivered, and the observer may not ask for places.
"""

import os
import stat
import subprocess
import threading
import time

import pytest
import zenoh
import zenoh.ext

from services.common import codec, topics
from services.common import service as service_base
from services.common.runtime import open_session
from tests.messages import sample_messages
from tests.netutil import free_port, port_open, start, stop, wait_for
from tests.tlsutil import (
    CLIENT_MTLS, CLIENT_TLS, ROUTER_MTLS_ACL, cfg_flags, client_runtime, make_certs, tls_endpoint,
)

ROBOT = "robot0"


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    return make_certs(tmp_path_factory.mktemp("certs"), "router-a.example", "10.1.2.3")


def test_make_certs_issues_verifiable_role_certificates(certs):
    def openssl(*args: str) -> str:
        return subprocess.run(["openssl", *args], capture_output=True, text=True, check=True).stdout

    for role in ("router", "source", "egomotion", "gridcells", "loopclosure", "expmap", "viewer", "fleetmap", "operator",
                 "observer"):
        assert openssl("verify", "-CAfile", str(certs / "ca.pem"), str(certs / f"{role}.pem")).strip().endswith("OK")
        assert f"CN = gridslam-{role}" in openssl("x509", "-in", str(certs / f"{role}.pem"), "-noout", "-subject")
        assert stat.S_IMODE(os.stat(certs / f"{role}.key").st_mode) == 0o600
    names = openssl("x509", "-in", str(certs / "router.pem"), "-noout", "-ext", "subjectAltName")
    for name in ("DNS:router", "DNS:localhost", "IP Address:127.0.0.1", "DNS:router-a.example", "IP Address:10.1.2.3"):
        assert name in names


@pytest.fixture(scope="module")
def acl_router(certs):
    """`gridslam router` with deploy/acl/router.json5; yields its port."""
    port = free_port()
    router = start(["router", "--listen", tls_endpoint(port, "127.0.0.1"), "--zenoh-config", str(ROUTER_MTLS_ACL),
                    *cfg_flags(certs, "router")])
    try:
        wait_for(lambda: port_open(port) or router.poll() is not None)
        assert router.poll() is None, router.communicate()[1]
        yield port
    finally:
        stop(router)


def health(port: int, certs, client_config, role: str) -> subprocess.CompletedProcess:
    args = ["health", "--timeout", "1", "-e", tls_endpoint(port), "--zenoh-config", str(client_config),
            *cfg_flags(certs, role)]
    process = start(args)
    out, err = process.communicate(timeout=30)
    return subprocess.CompletedProcess(args, process.returncode, out, err)


class Collector:
    """Decoded messages of one subscription, by arrival."""

    def __init__(self, session: zenoh.Session, key: str):
        self.messages = []
        self._lock = threading.Lock()
        self._subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.messages.append(codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding)))

    def seqs(self) -> list[int]:
        with self._lock:
            return [message.header.seq for message in self.messages]


def publish_egomotion(session: zenoh.Session, seq: int) -> None:
    message = next(m for m in sample_messages(seq) if m.KIND == "EgoMotion")
    session.put(topics.key(ROBOT, "egomotion"), codec.encode(message), encoding=zenoh.Encoding(codec.encoding_of(message)))


@pytest.fixture(scope="module")
def gridcells(acl_router, certs):
    """A real `gridslam service gridcells` holding the gridcells certificate; yields (port, instance)."""
    port, instance = acl_router, "acl"
    service = start(["service", "gridcells", "--integrator", "deadreckoning", "--instance", instance, "-e",
                     tls_endpoint(port), "--zenoh-config", str(CLIENT_MTLS), *cfg_flags(certs, "gridcells")])
    operator = open_session(client_runtime(port, CLIENT_MTLS, certs, "operator"))
    try:
        health_key = topics.health_key(ROBOT, "gridcells", instance)
        wait_for(lambda: service.poll() is not None or any(
            r.ok and str(r.ok.key_expr) == health_key
            for r in operator.liveliness().get(f"{topics.PREFIX}/{ROBOT}/health/**", timeout=1)), timeout=20)
        assert service.poll() is None, service.communicate()[1]
        yield port, instance
        assert service.poll() is None
    finally:
        operator.close()
        code, _, err = stop(service)
    assert code == 0, err


def test_access_control_lets_only_the_pipeline_publish_pipeline_keys(gridcells, certs):
    port, _ = gridcells
    sessions = {}
    try:
        # The observer certificate twice: one session publishes, the other watches (a session
        # delivers its own publications to its own subscribers without the router).
        for name, role in (("egomotion", "egomotion"), ("intruder", "observer"), ("watcher", "observer"),
                           ("operator", "operator")):
            sessions[name] = open_session(client_runtime(port, CLIENT_MTLS, certs, role))
        poses = Collector(sessions["watcher"], topics.key(ROBOT, "grid/pose"))
        watcher_egomotion = Collector(sessions["watcher"], topics.key(ROBOT, "egomotion"))
        operator_egomotion = Collector(sessions["operator"], topics.key(ROBOT, "egomotion"))
        time.sleep(0.3)   # let the declarations reach the router

        # The outside client publishes on a pipeline key first: nothing may come of it.
        for seq in (1, 2, 3):
            publish_egomotion(sessions["intruder"], seq)
        time.sleep(0.5)
        # Then the authorised publisher, with later frame numbers, until gridcells has answered.
        authorised = iter(range(10, 1000))

        def gridcells_answered():
            publish_egomotion(sessions["egomotion"], next(authorised))
            return [seq for seq in poses.seqs() if seq >= 10]
        wait_for(gridcells_answered, timeout=15, period=0.1)

        assert poses.seqs() and all(seq >= 10 for seq in poses.seqs()), poses.seqs()
        assert operator_egomotion.seqs() and all(seq >= 10 for seq in operator_egomotion.seqs()), operator_egomotion.seqs()
        assert watcher_egomotion.seqs() == []   # nor may the outside client read pipeline keys
    finally:
        for session in sessions.values():
            session.close()


def test_health_lists_services_only_for_the_operator(gridcells, certs):
    port, instance = gridcells

    def listed():
        result = health(port, certs, CLIENT_MTLS, "operator")
        assert result.returncode == 0, result.stderr
        return [line.split() for line in result.stdout.splitlines() if " gridcells " in f" {line} "]
    # liveliness token and status query both pass the access control: the row has its counters
    assert wait_for(listed, timeout=20, period=0.2)[0][:4] == [ROBOT, "gridcells", instance, "running"]

    # The outside client sees neither health tokens nor status.
    observer = open_session(client_runtime(port, CLIENT_MTLS, certs, "observer"))
    try:
        assert not [r for r in observer.liveliness().get(f"{topics.PREFIX}/{ROBOT}/health/**", timeout=1) if r.ok]
        assert not [r for r in observer.get(f"{topics.PREFIX}/{ROBOT}/status/**", timeout=1) if r.ok]
        # nor the router's admin space (a session answers `@/**` about itself only)
        routers = {str(zid) for zid in observer.info.routers_zid()}
        admin = {str(r.ok.key_expr).split("/")[1] for r in observer.get("@/**", timeout=1) if r.ok}
        assert routers and not admin & routers, admin
    finally:
        observer.close()

    anonymous = health(port, certs, CLIENT_TLS, "observer")   # trusts the router, presents no certificate
    assert anonymous.returncode == 1
    assert anonymous.stderr.strip().splitlines()[-1].startswith("gridslam health: error: cannot open a Zenoh session")


def test_status_query_is_answered_through_access_control(gridcells, certs):
    port, instance = gridcells
    operator = open_session(client_runtime(port, CLIENT_MTLS, certs, "operator"))
    try:
        replies = [r.ok for r in operator.get(f"{topics.PREFIX}/{ROBOT}/status/**", timeout=2) if r.ok]
        statuses = [codec.decode(r.payload.to_bytes(), encoding=str(r.encoding)) for r in replies]
        assert [(s.service, s.instance, s.state) for s in statuses] == [("gridcells", instance, "running")]
    finally:
        operator.close()


def test_sharding_and_the_refusal_pass_access_control(gridcells, certs):
    """Two egomotion instances see each other's shard tokens, and a second gridcells finds the
    first with its liveliness query: the rules deploy/acl/router.json5 grants them (docs/pipeline.md)."""
    port, instance = gridcells
    client = ["-e", tls_endpoint(port), "--zenoh-config", str(CLIENT_MTLS)]
    second = start(["service", "gridcells", "--integrator", "deadreckoning", "--instance", "second", *client,
                    *cfg_flags(certs, "gridcells")])
    try:
        _, err = second.communicate(timeout=60)
    finally:
        stop(second)   # still running if it was not refused
    assert second.returncode == 1 and f"gridcells of robot {ROBOT} is already running (instance {instance})" in err, err

    estimators = [start(["service", "egomotion", "--estimator", "passthrough", "--instances", "2", "--instance", name, *client,
                         *cfg_flags(certs, "egomotion")]) for name in ("one", "two")]
    sessions = [open_session(client_runtime(port, CLIENT_MTLS, certs, role)) for role in ("source", "operator")]
    try:
        source, operator = sessions
        frames = [next(m for m in sample_messages(seq) if m.KIND == "CameraFrame") for seq in range(6)]

        def members() -> dict[str, float]:
            replies = [r.ok for r in operator.get(f"{topics.PREFIX}/{ROBOT}/status/egomotion/*", timeout=1) if r.ok]
            return {s.instance: s.extra.get("shard_members", 0)
                    for s in (codec.decode(r.payload.to_bytes(), encoding=str(r.encoding)) for r in replies)}
        wait_for(lambda: len(members()) == 2, timeout=60, period=0.2)
        for frame in frames:   # the instances announce their share once they hold three frames
            source.put(topics.key(ROBOT, "camera/frame"), codec.encode(frame), encoding=zenoh.Encoding(codec.encoding_of(frame)))
        assert wait_for(lambda: members() == {"one": 2, "two": 2}, timeout=20, period=0.2)
    finally:
        for session in sessions:
            session.close()
        results = [stop(process) for process in estimators]
    assert all(code == 0 for code, _, _ in results), results


def test_the_publishers_cache_is_asked_through_access_control_by_the_topics_readers_only(acl_router, certs):
    """A pipeline publisher keeps its last samples in a cache that a subscriber which missed some
    asks (Zenoh's advanced publisher and subscriber, docs/reliability.md), under keys of their
    own (<topic>/@adv/...). A gridcells client that subscribes after egomotion published frames
    0-4 gets them from the cache; an observer, which may not read egomotion, gets none."""
    robot = "recovery"   # (the gridcells service of the other tests serves robot0)
    sessions = {role: open_session(client_runtime(acl_router, CLIENT_MTLS, certs, role))
                for role in ("egomotion", "gridcells", "observer")}
    got: dict[str, list[int]] = {"gridcells": [], "observer": []}
    subscribers = []
    try:
        publisher = service_base.declare_publisher(sessions["egomotion"], robot, "egomotion")
        for seq in range(5):
            publisher.put(codec.encode(next(m for m in sample_messages(seq) if m.KIND == "EgoMotion")))
        time.sleep(0.3)   # (the cache's queryable has reached the router)
        for role, seqs in got.items():
            subscribers.append(zenoh.ext.declare_advanced_subscriber(
                sessions[role], topics.key(robot, "egomotion"),
                lambda sample, seqs=seqs: seqs.append(codec.decode(sample.payload.to_bytes(),
                                                                   encoding=str(sample.encoding)).header.seq),
                history=zenoh.ext.HistoryConfig()))
        wait_for(lambda: len(got["gridcells"]) == 5, timeout=10)
        time.sleep(0.5)   # (time for the observer to get what it should not)
        assert got == {"gridcells": [0, 1, 2, 3, 4], "observer": []}
    finally:
        for session in sessions.values():
            session.close()


# --------------------------------------------------------------------------- a fleet
def put(session: zenoh.Session, robot: str, topic: str, message) -> None:
    session.put(topics.key(robot, topic), codec.encode(message), encoding=zenoh.Encoding(codec.encoding_of(message)))


def statuses_of(operator: zenoh.Session, robot: str, service: str) -> dict[str, float]:
    """The service's counters (its status's extra ones, and `received`), as the operator may ask."""
    replies = [r.ok for r in operator.get(f"{topics.PREFIX}/{robot}/status/{service}/*", timeout=1) if r.ok]
    found = [codec.decode(r.payload.to_bytes(), encoding=str(r.encoding)) for r in replies]
    return {**found[0].extra, "received": found[0].received} if found else {}


def own_places(status: dict[str, float]) -> int:
    """The places a robot's loopclosure made: sent live to a robot listening, or to no one yet."""
    return status.get("fleet_places_sent", 0) + status.get("fleet_places_unheard", 0)


@pytest.fixture(scope="module")
def fleet(acl_router, certs, tmp_path_factory):
    """Robots a and b's real loop closures (--fleet) and a real fleet map, each with its own
    certificate, on the access-controlled router; yields the port."""
    port, folder = acl_router, tmp_path_factory.mktemp("fleet")
    client = ["-e", tls_endpoint(port), "--zenoh-config", str(CLIENT_MTLS)]
    processes = [start(["service", "loopclosure", "--fleet", "--preset", "synthetic", "--robot", robot, "--instance", "acl",
                        "--store", str(folder / f"{robot}.log"), *client, *cfg_flags(certs, "loopclosure")])
                 for robot in ("a", "b")]
    processes.append(start(["service", "fleetmap", "--instance", "acl", "--frame-robot", "a", "--store",
                            str(folder / "fleet_map.log"), *client, *cfg_flags(certs, "fleetmap")]))
    operator = open_session(client_runtime(port, CLIENT_MTLS, certs, "operator"))
    try:
        wanted = {topics.health_key("a", "loopclosure", "acl"), topics.health_key("b", "loopclosure", "acl"),
                  topics.health_key(topics.FLEET, "fleetmap", "acl")}

        def up() -> bool:
            assert all(p.poll() is None for p in processes), [p.communicate()[1][-2000:] for p in processes if p.poll() is not None]
            return wanted <= {str(r.ok.key_expr) for r in operator.liveliness().get(f"{topics.PREFIX}/*/health/**", timeout=1)
                              if r.ok}
        wait_for(up, timeout=60, period=0.5)
        yield port
        assert all(p.poll() is None for p in processes)
    finally:
        operator.close()
        results = [stop(p, timeout=20) for p in processes]
    assert all(code == 0 for code, _, _ in results), [err[-2000:] for _, _, err in results]


def test_fleet_members_exchange_places_and_only_they_may(fleet, certs):
    from schemas import FleetPlaces, Header, PlaceRecord, Time
    from services.source.service import frame_message
    from services.source.synthetic import SyntheticWorld, WorldConfig

    port = fleet
    sessions = {role: open_session(client_runtime(port, CLIENT_MTLS, certs, role))
                for role in ("source", "operator", "observer")}
    try:
        world = SyntheticWorld(WorldConfig(seed=3, speed=0.25, laps=1))
        for robot, first in (("a", 0), ("b", 60)):   # each robot its own stretch of the corridor
            for seq in range(24):
                frame = world[first + seq]
                put(sessions["source"], robot, "camera/frame",
                    frame_message(frame, Header(seq=seq, stamp=Time.from_seconds(frame.stamp), frame_id="camera", robot=robot)))
        operator = sessions["operator"]

        def exchanged():   # every frame handled, and each robot learnt every place the other sent
            a, b = statuses_of(operator, "a", "loopclosure"), statuses_of(operator, "b", "loopclosure")
            sent_a, sent_b = own_places(a), own_places(b)
            return a.get("received", 0) >= 24 and b.get("received", 0) >= 24 and sent_a > 0 and sent_b > 0 and \
                a.get("fleet_places_learnt") == sent_b and b.get("fleet_places_learnt") == sent_a and (a, b)
        a, b = wait_for(exchanged, timeout=120, period=1.0)

        # The places queryable answers a reader with the right (the operator), not the observer.
        replies = [r.ok for r in operator.get(f"{topics.key('a', 'fleet/places')}?from=0", timeout=5) if r.ok]
        places = codec.decode(replies[0].payload.to_bytes(), FleetPlaces, str(replies[0].encoding))
        assert len(places.places) == own_places(a)
        assert not [r for r in sessions["observer"].get(f"{topics.key('a', 'fleet/places')}?from=0", timeout=2) if r.ok]

        # A place put by a certificate without the fleet's rights (a real keyframe, robot c) reaches nobody.
        forged = FleetPlaces(header=Header(seq=0, stamp=Time.from_seconds(0.0), frame_id="camera", robot="c"),
                             places=[PlaceRecord(place=0, frame=0, keyframe=places.places[0].keyframe)], place_count=1)
        for role in ("observer", "source"):
            put(sessions[role], "c", "fleet/place", forged)
        time.sleep(4)   # more than a sync period: the loop closures would have taken it by now
        # each learnt the other's places (read afresh: a robot may have stored more since), and nothing of c's
        def learnt_exactly_the_others():
            a, b = statuses_of(operator, "a", "loopclosure"), statuses_of(operator, "b", "loopclosure")
            return a["fleet_places_learnt"] == own_places(b) and b["fleet_places_learnt"] == own_places(a)
        wait_for(learnt_exactly_the_others, timeout=15, period=0.5)
    finally:
        for session in sessions.values():
            session.close()


def test_the_fleet_map_publishes_in_its_own_key_space_only(fleet, certs):
    from schemas import Experience, FleetPose, FleetSnapshot, Header, Link, MapPose, MapUpdate, Time
    from services.common.convert import planar_pose

    port = fleet
    sessions = {role: open_session(client_runtime(port, CLIENT_MTLS, certs, role))
                for role in ("expmap", "observer", "gridcells", "operator")}
    try:
        poses = Collector(sessions["observer"], f"{topics.PREFIX}/{topics.FLEET}/*/pose")   # an outside client may read these
        time.sleep(0.3)
        covariance = [0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.001]
        experiences = [Experience(id=i, x=float(i), y=0.0, heading=0.0, template_id=i, frame=10 * i) for i in range(3)]
        links = [Link(source=i, target=i + 1, dx=1.0, dy=0.0, dheading=0.0, frame=10 * (i + 1), covariance=covariance)
                 for i in range(2)]

        def header(seq: int) -> Header:
            return Header(seq=seq, stamp=Time.from_seconds(seq / 10), frame_id="map", robot="a")
        # An observer's map of robot a is not the fleet map's input; the expmap's is.
        put(sessions["observer"], "a", "map/update", MapUpdate(header=header(20), experiences=experiences + [
            Experience(id=3, x=50.0, y=50.0, heading=0.0, template_id=3, frame=20)], links=links, experience_count=4,
            link_count=2))
        time.sleep(0.5)
        put(sessions["expmap"], "a", "map/update", MapUpdate(header=header(20), experiences=experiences, links=links,
                                                             experience_count=3, link_count=2))

        def posed():
            put(sessions["expmap"], "a", "map/pose", MapPose(header=header(21), pose=planar_pose(2.1, 0.0, 0.0), heading=0.0,
                                                             experience_id=2))
            # a pipeline service without the fleet map's rights forges a fleet pose
            put(sessions["gridcells"], topics.FLEET, topics.fleet_pose_topic("a"), FleetPose(
                header=header(999), pose=planar_pose(9.0, 9.0, 0.0), heading=0.0, experience_id=0, joined=True))
            return poses.seqs()
        assert set(wait_for(posed, timeout=30, period=0.5)) == {21}
        message = poses.messages[0]
        assert message.joined and abs(message.pose.position.x - 2.1) < 1e-6

        replies = [r.ok for r in sessions["observer"].get(topics.key(topics.FLEET, "snapshot"), timeout=5) if r.ok]
        snapshot = codec.decode(replies[0].payload.to_bytes(), FleetSnapshot, str(replies[0].encoding))
        assert [(r.name, r.joined, r.experiences) for r in snapshot.robots] == [("a", True, 3)]
        assert statuses_of(sessions["operator"], topics.FLEET, "fleetmap")   # its status query passes
    finally:
        for session in sessions.values():
            session.close()
