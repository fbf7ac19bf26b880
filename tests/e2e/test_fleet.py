"""A fleet from the real command line (docs/fleet.md): two robots that start at different places
on the campus meet and end in one frame, the look-alike places between them refused; the fleet
map and one robot's loopclosure killed with SIGKILL mid-run and restarted by the runners,
catching up without losing a place or fusing anything twice; a robot joining mid-run, placed
soon after its first meeting; two sites, each robot on a router of its own, cut apart for a
while and joined again, losing no place."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.common.journal import read_records
from services.expmap.export import read_log
from services.pipeline.fleet import evaluate_fleet
from services.pipeline.runner import RunConfig
from tests.netutil import REPO, endpoint, free_port, ip, start, stop, veth_namespaces, wait_for

pytestmark = pytest.mark.serial   # which robot meets which place when: the robots' pace is part of what it tests


def pid_of(service: str, store: Path) -> int | None:
    """The process of `service` this test's run started with its store at `store`."""
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                command = (entry / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if service.encode() in command and str(store).encode() in command:
                return int(entry.name)
    return None


def fleet_journal(folder: Path) -> list[dict]:
    """Every other robot's place a robot's loopclosure has learnt (its fleet journal): robot, place, frame."""
    path = folder / "view_templates.fleet.log"
    return read_records(path)[0][1:] if path.exists() else []


def learnt_places(folder: Path) -> list[tuple[str, int]]:
    """(robot, place) of every other robot's place a robot's loopclosure has learnt."""
    return [(r["robot"], r["place"]) for r in fleet_journal(folder)]


def journal_inputs(out: Path) -> list[dict]:
    path = out / "fleet" / "fleet_map.log"
    return [r for r in read_records(path)[0][1:] if "checkpoint" not in r] if path.exists() else []


def test_two_robots_meet_on_the_campus_refuse_its_look_alikes_and_survive_kills(tmp_path):
    """Robot a from the campus route's frame 960, b from 3120 (some 950 m of route further on),
    300 frames each: b's frames 3160-3252 drive a's 960-1045 again (a true meeting, b joins there),
    and a's 1177-1216 drive the copy of the corridor b passed at its 3201-3240 (the look-alikes, 37 m
    from the places they copy: confirmed, and refused by the fleet map). a meets the look-alikes
    only if it has b's places of 3201-3240 by its 1177: b's loopclosure is killed once a has them
    (killed sooner, b once fell so far behind while it restarted that a passed 1177-1216 first)."""
    out = tmp_path / "fleet"
    run = start(["run", "--fleet", "--source", "synthetic:0", "--preset", "campus", "--egomotion", "passthrough",
                 "--n-frames", "300", "--robot-start", "960", "--robot-start", "3120", "--listen", endpoint(free_port()),
                 "--out", str(out)])
    try:
        # Once the fleet map has taken some of both robots' maps, kill it; the runner starts it again.
        wait_for(lambda: (out / "fleet" / "fleet_map.log").exists() and len(journal_inputs(out)) > 40
                 or run.poll() is not None, timeout=120, period=0.5)
        pid = pid_of("fleetmap", out / "fleet" / "fleet_map.log")
        assert pid is not None and run.poll() is None
        os.kill(pid, signal.SIGKILL)
        # And robot b's loopclosure, once it has learnt some of a's places and a has b's places of
        # the meeting and the look-alikes' corridor: b's run starts it again, and it learns what it
        # lacks, from its journal and from a, each place once.
        wait_for(lambda: len(learnt_places(out / "b")) >= 20 and any(r["frame"] > 3252 for r in fleet_journal(out / "a"))
                 or run.poll() is not None, timeout=120, period=0.5)
        pid = pid_of("loopclosure", out / "b" / "view_templates.log")
        assert pid is not None and run.poll() is None
        os.kill(pid, signal.SIGKILL)
        stdout, stderr = run.communicate(timeout=300)
        code = run.returncode
    finally:
        if run.poll() is None:
            stop(run)
    assert code == 0, stderr[-2000:]
    fleet = json.loads((out / "metrics.json").read_text())["fleet"]
    assert fleet["joined_at"]["a"] == 960 and fleet["joined_at"]["b"] is not None
    assert fleet["inter_robot_closures_accepted"] >= 20 and fleet["inter_robot_closures_accepted_false"] == 0
    assert fleet["inter_robot_closures_rejected_false"] > 0, fleet   # the look-alikes were met, and refused
    assert fleet["ate_m"]["b"] < 0.1
    # The poses published live after a robot joined: robot a's always, b's from its first meeting on.
    online = fleet["online_error_after_join_m"]
    assert "a" in online and all(error["max"] < 0.3 for error in online.values())
    # a robot joining mid-run: joined by closures soon after it first comes to a place the other saw
    # (placed live a little later: by then the fleet map was killed and caught up, `placed_at`)
    assert fleet["first_meeting"]["b"] is not None and fleet["joined_at"]["b"] - fleet["first_meeting"]["b"] <= 20
    assert fleet["placed_at"]["b"] >= fleet["joined_at"]["b"]
    assert fleet["fleetmap_restarts"] == 1   # and it resumed from its journal: every input once, below
    assert json.loads((out / "b" / "metrics.json").read_text())["services"]["loopclosure"]["restarts"] == 1
    learnt = learnt_places(out / "b")   # every place of a's up to its last, each once
    assert len(learnt) == len(set(learnt)) and {p for _, p in learnt} == set(range(len(learnt)))
    # nothing fused twice: each closure, and each part of a robot's map, once in the journal
    closures = [(r["closure"]["robot"], r["closure"]["index"]) for r in journal_inputs(out) if "closure" in r]
    assert len(closures) == len(set(closures)) == fleet["inter_robot_closures_confirmed"]
    experiences = [(r["map"], e[0]) for r in journal_inputs(out) if "map" in r for e in r["experiences"]]
    assert len(experiences) == len(set(experiences))
    for robot in ("a", "b"):
        assert (out / "fleet" / f"{robot}.tum").stat().st_size > 0
        assert (out / "fleet" / f"{robot}.groundtruth.tum").stat().st_size > 0
        if robot in online:   # the fleet poses as published from its join on, one row each
            published = (out / "fleet" / f"{robot}.online.tum").read_text().splitlines()
            assert len([row for row in published if not row.startswith("#")]) == online[robot]["frames"]
        # what a robot sent the other (its places' keyframes, never images): some, and at most 5 % of its camera data
        counters = json.loads((out / robot / "metrics.json").read_text())["services"]["loopclosure"]["extra"]
        assert 0 < counters["fleet_bytes_sent"] <= 0.05 * counters["camera_bytes"], counters


def test_a_robot_joining_mid_run_is_placed_within_20_frames_of_its_first_meeting(tmp_path):
    """Robot b starts where a started once a has done 80 of its 160 frames on the corridor world:
    b's first frame is a place a saw. a's places made before anyone listened reach b when it asks
    for them, a's stack parked on the network once its frames are done."""
    out = tmp_path / "fleet"
    run = start(["run", "--fleet", "--source", "synthetic:0", "--preset", "synthetic", "--egomotion", "passthrough",
                 "--n-frames", "160", "--robot-start", "0", "--robot-start", "0", "--robot-delay", "0",
                 "--robot-delay", "80", "--listen", endpoint(free_port()), "--out", str(out)])
    try:
        stdout, stderr = run.communicate(timeout=300)
    finally:
        if run.poll() is None:
            stop(run)
    assert run.returncode == 0, stderr[-2000:]
    assert "robot b: frames from 0, after robot a's first 80" in stderr + stdout
    fleet = json.loads((out / "metrics.json").read_text())["fleet"]
    assert fleet["first_meeting"]["b"] == 0 and fleet["joined_at"]["b"] is not None
    assert 0 <= fleet["frames_to_join"]["b"] <= 20
    assert fleet["inter_robot_closures_accepted"] > 0 and fleet["inter_robot_closures_accepted_false"] == 0
    assert fleet["ate_m"]["b"] < 0.1 and fleet["online_error_after_join_m"]["b"]["max"] < 0.1
    counters = {robot: json.loads((out / robot / "metrics.json").read_text())["services"]["loopclosure"]["extra"]
                for robot in ("a", "b")}
    # b came late: a's first places reached no one, and were sent again when b asked for them
    assert counters["a"]["fleet_places_unheard"] > 0 and counters["a"]["fleet_places_resent"] > 0
    learnt = learnt_places(out / "b")   # every place of a's, each once
    assert sorted(p for _, p in learnt) == list(range(int(counters["a"]["templates"])))
    # a stayed on the network once its frames were done: it learnt every place of b's, the last ones
    # made some 80 frames after a's last
    assert sorted(p for _, p in learnt_places(out / "a")) == list(range(int(counters["b"]["templates"])))


def places_of(folder: Path) -> set[int]:
    """The places a robot's loop closure has stored (its journal)."""
    return {r["template"] for r in read_records(folder / "view_templates.log")[0][1:] if r.get("new")}


@pytest.fixture
def two_sites():
    """Namespaces joined by a veth pair, 10.232.0.1 (site A) and 10.232.0.2 (site B); yields them
    and the link's device in B, which a test sets down to cut the sites apart."""
    with veth_namespaces(("gs-fa", "gs-fb"), ("gfa", "gfb"), "10.232.0") as sites:
        yield sites


def in_ns(ns: str, args: list[str], log: Path) -> subprocess.Popen:
    handle = open(log, "w")
    return subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, *args], cwd=REPO, stdout=handle,
                            stderr=subprocess.STDOUT, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})


def test_two_sites_cut_apart_and_joined_again_lose_no_place_and_fuse_nothing_twice(two_sites, tmp_path):
    site_a, site_b, link_b = two_sites
    router_a, router_b = "tcp/10.232.0.1:7447", "tcp/10.232.0.2:7447"
    processes = [in_ns(site_a, ["-m", "services.cli", "router", "--listen", router_a], tmp_path / "router-a.log")]
    processes.append(in_ns(site_b, ["-m", "services.cli", "router", "--listen", router_b, "-e", router_a],
                           tmp_path / "router-b.log"))
    (tmp_path / "fleet").mkdir()
    processes.append(in_ns(site_a, ["-m", "services.cli", "service", "fleetmap", "-e", router_a, "--instance", "fleetmap",
                                    "--store", str(tmp_path / "fleet" / "fleet_map.log"), "--frame-robot", "a"],
                           tmp_path / "fleetmap.log"))
    members = {}
    try:
        time.sleep(3)
        # Paced (12 frames/s, 20 s a robot) so that both are still running when the 10 s cut ends,
        # however fast the machine.
        paced = tmp_path / "paced.toml"
        paced.write_text("[source]\nrate = 12.0\n")
        base = RunConfig(source="synthetic:0", preset="synthetic", egomotion="passthrough", n_frames=240, fleet=True,
                         origin=0, mcap=False, config_file=paced)
        for robot, start_frame, site, router in (("a", 0, site_a, router_a), ("b", 120, site_b, router_b)):
            folder = tmp_path / robot
            folder.mkdir()
            (folder / "member.json").write_text(base.model_copy(update={"robot": robot, "start": start_frame,
                                                                        "connect": router}).model_dump_json())
            members[robot] = in_ns(site, ["-m", "services.pipeline.fleet_member", str(folder / "member.json"),
                                          str(folder)], tmp_path / f"member-{robot}.log")
        # Once b's map is in the fleet map and the robots have each other's first places: cut.
        wait_for(lambda: any(r.get("map") == "b" for r in journal_inputs(tmp_path))
                 and (tmp_path / "a" / "view_templates.fleet.log").exists(), timeout=120, period=0.5)
        ip("-n", site_b, "link", "set", link_b, "down")
        before = {robot: places_of(tmp_path / robot) for robot in ("a", "b")}
        time.sleep(10)
        stored = {robot: places_of(tmp_path / robot) for robot in ("a", "b")}
        ip("-n", site_b, "link", "set", link_b, "up")
        # places were stored while the sites were apart; every one must reach the other robot
        assert any(stored[robot] - before[robot] for robot in ("a", "b")), "no place stored while cut apart"
        assert all(member.poll() is None for member in members.values())   # both still running to catch up
        for robot, member in members.items():
            assert member.wait(timeout=300) == 0, (tmp_path / f"member-{robot}.log").read_text()[-2000:]
        # the fleet map's last catch-up (it asks every sync_period, 3 s)
        sizes = {robot: len(read_log(tmp_path / robot / "experience_map.log").rebuild()) for robot in ("a", "b")}
        wait_for(lambda: all(sum(len(r["experiences"]) for r in journal_inputs(tmp_path) if r.get("map") == robot)
                             == size for robot, size in sizes.items()), timeout=30, period=0.5)
    finally:
        for process in [*members.values(), *reversed(processes)]:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
                try:
                    process.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    process.kill()
    inputs = journal_inputs(tmp_path)
    # No place lost: each robot learnt, once, every place the other had stored when the sites were joined
    # again (those stored while they were apart included), and nothing is missing before its last.
    for robot, other in (("a", "b"), ("b", "a")):
        learnt = learnt_places(tmp_path / robot)
        places = {p for _, p in learnt}
        assert len(learnt) == len(places) and places == set(range(len(places)))
        assert stored[other] and stored[other] <= places
    # The fleet map has every robot's whole map and every closure, each once.
    for robot in ("a", "b"):
        experiences = [e[0] for r in inputs if r.get("map") == robot for e in r["experiences"]]
        assert experiences == list(range(len(experiences)))
        assert len(experiences) == len(read_log(tmp_path / robot / "experience_map.log").rebuild())
    closures = [(r["closure"]["robot"], r["closure"]["index"]) for r in inputs if "closure" in r]
    assert len(closures) == len(set(closures)) > 0
    # each closure confirmed by votes its robot journaled: a frame's own, or its late match's (`fleet_late`)
    votes = sum(len(r.get("fleet", ())) + sum(len(late) for _, late in r.get("fleet_late", ()))
                for robot in ("a", "b") for r in read_records(tmp_path / robot / "view_templates.log")[0][1:])
    assert votes >= len(closures)
    fleet = evaluate_fleet(tmp_path, ["a", "b"], {}, {"a": 0, "b": 0})
    assert fleet["joined_at"]["b"] is not None and fleet["inter_robot_closures_accepted_false"] == 0
    assert fleet["ate_m"]["b"] < 0.1


def test_the_ros2_node_publishes_every_joined_robot_in_the_shared_map_frame(tmp_path):
    from schemas import FleetPose, Header, Time
    from services.common import codec, topics
    from services.common.convert import planar_pose
    from tests.netutil import client_session, port_open
    from tests.ros2client import Client

    port = free_port()
    router = start(["router", "--listen", endpoint(port)])
    node = None
    client = session = None
    try:
        wait_for(lambda: port_open(port), timeout=15)
        node = start(["service", "ros2", "--fleet", "-e", endpoint(port), "--instance", "ros2"])
        client = Client(port, tmp_path / "msgs")
        for robot in ("a", "b"):
            client.subscribe(f"/fleet/{robot}/pose", "geometry_msgs/msg/PoseWithCovarianceStamped")
        session = client_session(port, robot=topics.FLEET)
        time.sleep(3)   # the node's subscription and the client's discovery

        def publish(robot: str, seq: int, joined: bool) -> None:
            message = FleetPose(header=Header(seq=seq, stamp=Time.from_seconds(seq / 10), frame_id="map", robot=robot),
                                pose=planar_pose(seq * 0.1, 1.0, 0.5), heading=0.5, experience_id=seq, joined=joined)
            session.put(topics.key(topics.FLEET, topics.fleet_pose_topic(robot)), codec.encode(message),
                        encoding=codec.encoding_of(message))

        def heard() -> bool:
            for seq in range(5):
                publish("a", seq, True)
                publish("b", seq, seq >= 3)   # b joins at its frame 3
            time.sleep(0.3)
            return len(client.received["/fleet/a/pose"]) >= 5 and len(client.received["/fleet/b/pose"]) >= 2

        wait_for(heard, timeout=40, period=0.5)
    finally:
        if session is not None:
            session.close()
        if client is not None:
            client.close()
        for process in (node, router):
            if process is not None:
                stop(process)
    poses_b = client.received["/fleet/b/pose"]
    assert all(m.header.frame_id == "map" for m in client.received["/fleet/a/pose"] + poses_b)
    assert {round(m.pose.pose.position.x, 6) for m in poses_b} <= {0.3, 0.4}   # only once joined
