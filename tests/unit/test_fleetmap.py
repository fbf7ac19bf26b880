"""The fleet map's core (services/fleetmap/graph.py, consistency.py, store.py): two robots' maps
on one loop, joined by consistent inter-robot closures, look-alike closures refused or split
away, and a journal that rebuilds the same map."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from services.common.geometry import between, compose
from services.fleetmap.catchup import ClosureIntake, map_increment
from services.fleetmap.consistency import Candidate, ConsistencyParams, consistency_graph, maximum_clique
from services.fleetmap.graph import ClosureInput, FleetMap, FleetParams
from services.common.journal import read_records
from services.fleetmap.store import FleetStore, apply, closure_record, map_record, read_fleet_log

COVARIANCE = (0.01 ** 2, 0, 0, 0, 0.01 ** 2, 0, 0, 0, 1e-4)
LINK_COVARIANCE = list(np.diag([1e-4, 1e-4, 1e-6]).ravel())
LOOP = [(10 * math.cos(2 * math.pi * i / 120), 10 * math.sin(2 * math.pi * i / 120), 2 * math.pi * i / 120 + math.pi / 2)
        for i in range(120)]


def robot(start: int, count: int = 60):
    """A robot driving the 10 m loop from its pose `start`: true poses, its map's experiences (in
    its own frame: its first pose at the origin) and odometric links."""
    truth = [LOOP[(start + i) % len(LOOP)] for i in range(count)]
    mine = [between(truth[0], p) for p in truth]
    experiences = [(i, *mine[i], i) for i in range(count)]
    links = [(i - 1, i, *between(mine[i - 1], mine[i]), False, True, LINK_COVARIANCE) for i in range(1, count)]
    return truth, experiences, links


def closure(index, experience, truth_b, matched, truth_a, claimed=None):
    """Robot b's experience revisits robot a's; `claimed`: the relative pose a look-alike shows."""
    pose = claimed if claimed is not None else between(truth_a[matched], truth_b[experience])
    return ClosureInput("b", index, experience, experience, (0.0, 0.0, 0.0), "a", matched, matched, (0.0, 0.0, 0.0),
                        "stereo", pose, COVARIANCE)


def error_of_b(fleet, truth_a, truth_b):
    return max(math.dist(fleet.pose("b", i)[:2], between(truth_a[0], truth_b[i])[:2]) for i in range(len(truth_b)))


@pytest.fixture
def two():
    truth_a, ea, la = robot(0)
    truth_b, eb, lb = robot(40)
    fleet = FleetMap(FleetParams(frame_robot="a"))
    fleet.add_map("a", ea, la)
    fleet.add_map("b", eb, lb)
    return fleet, truth_a, truth_b


def test_consistent_closures_join_a_robot_in_the_first_robots_frame(two):
    fleet, truth_a, truth_b = two
    assert not fleet.joined("b") and fleet.joined("a")
    assert error_of_b(fleet, truth_a, truth_b) > 5   # its own frame: elsewhere on the loop
    fates = []
    for k in range(6):
        result = fleet.add_closure(closure(k, k, truth_b, 40 + k, truth_a))
        fates.append(fleet.joined("b"))
    assert fates == [False, False, True, True, True, True]   # join_closures = 3
    assert fleet.joined_at["b"] == 2
    assert error_of_b(fleet, truth_a, truth_b) < 1e-6
    assert fleet.counts()["accepted"] == 6 and not result.joined


def test_a_look_alike_after_the_join_is_refused_and_does_not_bend_the_map(two):
    fleet, truth_a, truth_b = two
    for k in range(5):
        fleet.add_closure(closure(k, k, truth_b, 40 + k, truth_a))
    before = fleet.estimates["b"].copy()
    for k in range(5, 13):   # b's experiences 30.. look like a's 10.., 20 experiences (10 m) away
        result = fleet.add_closure(closure(k, 25 + k, truth_b, 5 + k, truth_a, claimed=(0.05, 0.0, 0.01)))
        assert [c.fate for c in result.decided] == ["rejected"] and result.decided[0].statistic > 100
    change = fleet.estimates["b"] - before
    change[:, 2] = (change[:, 2] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(change).max() < 1e-6
    assert error_of_b(fleet, truth_a, truth_b) < 1e-6


def test_look_alikes_first_join_wrongly_and_the_true_closures_split_them_and_join_them_right(two):
    fleet, truth_a, truth_b = two
    for k in range(6):   # the only evidence at first: a look-alike
        fleet.add_closure(closure(k, 30 + k, truth_b, 10 + k, truth_a, claimed=(0.0, 0.0, 0.0)))
    assert fleet.joined("b") and error_of_b(fleet, truth_a, truth_b) > 5
    splits = []
    for k in range(6, 26):
        splits += fleet.add_closure(closure(k, k - 6, truth_b, 40 + k - 6, truth_a)).split
    assert splits == [("b", "a")]
    assert fleet.joined("b") and error_of_b(fleet, truth_a, truth_b) < 1e-6
    fates = [c.fate for c in fleet.closures]
    assert fates[:6] == ["rejected"] * 6 and set(fates[6:]) == {"accepted"}



def test_a_far_off_closure_refused_after_the_join_leaves_the_map_as_it_was():
    """Robot a drives 1⅓ laps with a biased odometry and closes its own loop (closures under the
    kernel); a closure that says b is turned round is refused, and taking it out again must not
    leave the map in the bent shape the test solved it into."""
    rng = np.random.default_rng(1)
    truth_a = [LOOP[i % len(LOOP)] for i in range(160)]
    mine = [(0.0, 0.0, 0.0)]
    links_a = []
    for i in range(1, 160):
        step = between(truth_a[i - 1], truth_a[i])
        step = (step[0] * 1.01 + rng.normal(0, 0.005), step[1] + rng.normal(0, 0.005), step[2] + 0.002)
        links_a.append((i - 1, i, *step, False, True, LINK_COVARIANCE))
        mine.append(compose(mine[-1], step))
    links_a += [(i - 120, i, *between(truth_a[i - 120], truth_a[i]), True, True, list(np.diag([1e-4, 1e-4, 1e-5]).ravel()))
                for i in range(120, 160)]
    truth_b, eb, lb = robot(40)
    fleet = FleetMap(FleetParams(frame_robot="a"))
    fleet.add_map("a", [(i, *mine[i], i) for i in range(160)], links_a)
    fleet.add_map("b", eb, lb)
    for k in range(5):
        fleet.add_closure(closure(k, k, truth_b, 40 + k, truth_a))
    assert fleet.joined("b")
    before = {name: estimates.copy() for name, estimates in fleet.estimates.items()}
    result = fleet.add_closure(closure(5, 30, truth_b, 130, truth_a, claimed=(0.0, 0.0, 3.0)))
    assert [c.fate for c in result.decided] == ["rejected"] and result.decided[0].statistic > 100
    for name in ("a", "b"):   # (without the fresh solve from the map as it was: 21 mm)
        assert np.abs(fleet.estimates[name][:, :2] - before[name][:, :2]).max() < 0.002


def test_a_span_longer_than_the_look_alikes_keeps_them_from_joining(two):
    _, truth_a, truth_b = two
    fleet = FleetMap(FleetParams(frame_robot="a", join_span=8.0))
    for name, (_, e, links) in (("a", robot(0)), ("b", robot(40))):
        fleet.add_map(name, e, links)
    for k in range(8):   # eight closures over 3.5 m of each map
        fleet.add_closure(closure(k, 30 + k, truth_b, 10 + k, truth_a, claimed=(0.0, 0.0, 0.0)))
    assert not fleet.joined("b")
    for k in range(8, 28):   # true ones over 10 m
        fleet.add_closure(closure(k, k - 8, truth_b, 40 + k - 8, truth_a))
    assert fleet.joined("b") and error_of_b(fleet, truth_a, truth_b) < 1e-6
    assert all(c.fate == "rejected" for c in fleet.closures[:8])


def test_a_closure_to_a_place_with_a_known_look_alike_joins_nothing():
    truth_a, ea, la = robot(0)
    truth_b, eb, lb = robot(40)
    la = la + [(30, 10, 0.0, 0.0, 0.0, True, False, LINK_COVARIANCE)]   # a's own map refused 30 ↔ 10
    fleet = FleetMap(FleetParams(frame_robot="a"))
    fleet.add_map("a", ea, la)
    fleet.add_map("b", eb, lb)
    for k in range(5):
        fleet.add_closure(closure(k, 20 + k % 1, truth_b, 10, truth_a))
    assert not fleet.joined("b") and {c.fate for c in fleet.closures} == {"rejected"}


def test_a_closure_is_taken_once(two):
    fleet, truth_a, truth_b = two
    for _ in range(2):
        for k in range(4):
            fleet.add_closure(closure(k, k, truth_b, 40 + k, truth_a))
    assert len(fleet.closures) == 4


def test_pairwise_consistency_and_the_maximum_clique():
    params = ConsistencyParams()
    link = (1.0, 0.0, 0.0)
    good = [Candidate(i, (float(i), 0.0, 0.0), (float(i) - 1.0, 0.0, 0.0), link, np.eye(3) * 1e-4) for i in range(4)]
    bad = [Candidate(10 + i, (float(i), 0.0, 0.0), (float(i) + 30.0, 0.0, 0.0), link, np.eye(3) * 1e-4) for i in range(2)]
    neighbours = consistency_graph(good + bad, params)
    assert neighbours[0] == {1, 2, 3} and neighbours[10] == {11}
    assert maximum_clique(neighbours) == [0, 1, 2, 3]
    assert maximum_clique(neighbours, {10, 11, 2}) == [10, 11]


def test_the_journal_and_its_checkpoint_rebuild_the_same_map(tmp_path):
    truth_a, ea, la = robot(0)
    truth_b, eb, lb = robot(40)
    records = [map_record("a", ea[:30], la[:29]), map_record("b", eb, lb), map_record("a", ea[30:], la[29:])]
    records += [closure_record(closure(k, k, truth_b, 40 + k, truth_a)) for k in range(8)]
    records += [closure_record(closure(8, 30, truth_b, 10, truth_a, claimed=(0.0, 0.0, 0.0)))]
    params, consistency = FleetParams(frame_robot="a"), ConsistencyParams()
    store = FleetStore(tmp_path / "fleet.log", params, consistency, checkpoint_events=5)
    live = FleetMap(params, consistency)
    for record in records:
        store.append(record)
        apply(live, record)
        if store.checkpoint_due():
            store.checkpoint(live)
    store.close()
    reopened = FleetStore(tmp_path / "fleet.log", params, consistency, checkpoint_events=5)
    restored, start = reopened.rebuild()
    assert start == 10
    (tmp_path / "fleet.log.checkpoint.json").unlink()
    replayed, start = FleetStore(tmp_path / "fleet.log", params, consistency, 5).rebuild()
    assert start == 0
    for fleet in (restored, replayed, read_fleet_log(tmp_path / "fleet.log")):
        for name in ("a", "b"):
            assert np.array_equal(fleet.estimates[name], live.estimates[name])
        assert [c.fate for c in fleet.closures] == [c.fate for c in live.closures]
    assert live.closures[-1].fate == "rejected"
    # restart-exact: the restored maps go on as the live one does
    later = [closure_record(closure(k, k + 2, truth_b, 42 + k, truth_a)) for k in range(9, 13)]
    later.append(closure_record(closure(13, 40, truth_b, 20, truth_a, claimed=(0.0, 0.0, 0.0))))
    fates = [[[c.fate for c in apply(fleet, record).decided] for record in later] for fleet in (live, restored, replayed)]
    assert fates == [[["accepted"]] * 4 + [["rejected"]]] * 3
    for fleet in (restored, replayed):
        for name in ("a", "b"):
            assert np.array_equal(fleet.estimates[name], live.estimates[name])


def test_a_join_needs_mutually_consistent_closures(two):
    fleet, truth_a, truth_b = two
    # six closures that each say b's map is somewhere else: every one 1 m to the side of the last
    for k in range(6):
        true = between(truth_a[40 + k], truth_b[k])
        fleet.add_closure(closure(k, k, truth_b, 40 + k, truth_a, claimed=(true[0], true[1] + 1.0 * k, true[2])))
    assert not fleet.joined("b") and {c.fate for c in fleet.closures} == {"pending"}
    assert error_of_b(fleet, truth_a, truth_b) > 5   # still in its own frame


def test_a_single_look_alike_among_true_closures_joins_nothing_and_is_refused(two):
    fleet, truth_a, truth_b = two
    # b's experience 30 looks like a's 10 (the pose says: right there), then two true closures
    fleet.add_closure(closure(0, 30, truth_b, 10, truth_a, claimed=(0.0, 0.0, 0.0)))
    for k in range(1, 3):
        fleet.add_closure(closure(k, k, truth_b, 40 + k, truth_a))
    assert not fleet.joined("b")   # three closures, but only two agree: join_closures = 3
    fleet.add_closure(closure(3, 3, truth_b, 43, truth_a))
    assert fleet.joined("b") and error_of_b(fleet, truth_a, truth_b) < 1e-6
    assert [c.fate for c in fleet.closures] == ["rejected", "accepted", "accepted", "accepted"]



def updates(experiences, links, cuts, relisted=2):
    """A robot's map/update stream: one message per stretch between ``cuts``, each with its new
    experiences (and the ``relisted`` before them again, as a map a closure moved relists them),
    its new links and the map's link count after it."""
    def shown(lo, hi):
        return [SimpleNamespace(id=e[0], x=e[1], y=e[2], heading=e[3], frame=e[4]) for e in experiences[lo:hi]]
    return [SimpleNamespace(experiences=shown(max(0, lo - relisted), hi), links=links[max(0, lo - 1):hi - 1],
                            link_count=hi - 1) for lo, hi in zip(cuts, cuts[1:])]


class Adapter:
    """What the fleetmap service does with what it hears of robot b (services/fleetmap/service.py),
    without Zenoh: map messages through `map_increment`, closures through a `ClosureIntake`, every
    input journaled before it is applied (a restart: `FleetStore.rebuild`, the intake told of the
    replayed closures)."""

    def __init__(self, path, records):
        self.store = FleetStore(path, FleetParams(frame_robot="a"), ConsistencyParams(), checkpoint_events=4)
        self.intake = ClosureIntake()
        self.records = records
        self.fleet, _ = self.store.rebuild(
            each=lambda record, _: "closure" in record and self.intake.replayed("b", record["closure"]["index"]))

    def grow(self, robot, experiences, links):
        self.apply(map_record(robot, [(e.id, e.x, e.y, e.heading, e.frame) for e in experiences], links))

    def apply(self, record):
        self.store.append(record)
        apply(self.fleet, record)
        if self.store.checkpoint_due():
            self.store.checkpoint(self.fleet)

    def map_message(self, message, snapshot=False):
        """A map/update (a snapshot: all links, from the first); False when it does not follow on."""
        state = self.fleet.robots.get("b")
        increment = map_increment(len(state.poses) if state else 0, state.links if state else 0, message.experiences,
                                  0 if snapshot else message.link_count - len(message.links), message.links)
        if increment is not None:
            self.grow("b", *increment)
            self.resolve()
        return increment is not None

    def closures(self, indices):
        taken = self.intake.take("b", [self.records[k] for k in indices])
        self.resolve()
        return [record.index for record in taken]

    def resolve(self):
        for _, _, placed in self.intake.place(self.placement):
            self.apply(closure_record(placed))

    def placement(self, _robot, record):   # placed once b's map has the revisiting experience
        return record.closure if record.closure.experience < len(self.fleet.robots["b"].poses) else None


def test_catching_up_live_late_and_after_a_restart_fuses_nothing_twice(two, tmp_path):
    reference, truth_a, truth_b = two
    closures = [closure(k, 2 * k, truth_b, 40 + 2 * k, truth_a) for k in range(10)]
    for c in closures:
        reference.add_closure(c)
    assert reference.joined("b")
    _, ea, la = robot(0)
    _, eb, lb = robot(40)
    records = [SimpleNamespace(index=c.index, closure=c) for c in closures]
    stream = updates(eb, lb, [0, 2, 6, 20, 30, 45, 60])
    snapshot = SimpleNamespace(experiences=updates(eb, lb, [0, 30], relisted=0)[0].experiences, links=lb[:29])
    fleet = Adapter(tmp_path / "fleet.log", records)
    fleet.grow("a", updates(ea, la, [0, 60])[0].experiences, la)
    assert fleet.map_message(stream[0]) and fleet.closures([0, 1]) == [0, 1]
    assert [r.index for _, r in fleet.intake.waiting] == [1]   # it revisits experience 2, not on the map yet
    assert fleet.map_message(stream[1]) and not fleet.intake.waiting
    # stream[2] (experiences 6..19) and closures 2, 3 go by unheard
    assert not fleet.map_message(stream[3])                       # does not follow on: the snapshot
    assert fleet.map_message(snapshot, snapshot=True)
    assert fleet.map_message(stream[3]) and fleet.map_message(stream[2])   # heard late: nothing new in them
    assert fleet.intake.missed("b", records[4:5]) and fleet.closures([4]) == []   # a gap: asked from closure 2
    assert fleet.closures(range(2, 7)) == [2, 3, 4, 5, 6] and fleet.closures([4, 5]) == []
    assert fleet.intake.duplicates == 2
    fleet.store.close()
    # restarted: its journal (and checkpoint) replayed, then everything heard again from the start
    fleet = Adapter(tmp_path / "fleet.log", records)
    assert fleet.store.checkpoints and fleet.intake.next == {"b": 7}
    for message in stream:
        assert fleet.map_message(message)
    assert fleet.closures(range(10)) == [7, 8, 9]
    fleet.store.close()
    journal = [r for r in read_records(tmp_path / "fleet.log")[0][1:] if "checkpoint" not in r]
    assert [e[0] for r in journal if r.get("map") == "b" for e in r["experiences"]] == list(range(60))
    assert [r["closure"]["index"] for r in journal if "closure" in r] == list(range(10))
    rebuilt = read_fleet_log(tmp_path / "fleet.log")
    for result in (fleet.fleet, rebuilt):
        assert result.robots["b"].links == 59
        assert [(c.ident, c.fate) for c in result.closures] == [(c.ident, c.fate) for c in reference.closures]
        for name in ("a", "b"):
            assert np.allclose(result.estimates[name], reference.estimates[name], atol=1e-9)
    for name in ("a", "b"):
        assert np.array_equal(rebuilt.estimates[name], fleet.fleet.estimates[name])


def test_a_robot_met_at_its_own_places_is_placed_at_its_newest_frame():
    """Robot a revisits the places robot b passed before (b ahead of it on the loop): the join's
    closures name b's frames long past; placed_at is b's newest frame the map had heard of, within
    the three closures a join takes of the first one."""
    truth_a, ea, la = robot(0)
    truth_b, eb, lb = robot(40)
    fleet = FleetMap(FleetParams(frame_robot="a"))
    fleet.add_map("a", ea[:1], [])
    fleet.add_map("b", eb[:30], lb[:29])   # b's map up to its frame 29
    first = None
    for k in range(30):   # a's experience 40 + k is b's k: a drives behind b, b one experience a frame
        fleet.add_map("a", ea[len(fleet.robots["a"].poses):41 + k], la[len(fleet.robots["a"].poses) - 1:40 + k])
        fleet.add_map("b", eb[30 + k:31 + k], lb[29 + k:30 + k])
        pose = between(truth_b[k], truth_a[40 + k])   # a's frame 40 + k in b's place k's frame
        fleet.add_closure(ClosureInput("a", k, 40 + k, 40 + k, (0.0, 0.0, 0.0), "b", k, k, (0.0, 0.0, 0.0),
                                       "stereo", pose, COVARIANCE))
        first = 30 + k if first is None else first   # b's newest frame at the first closure
        if fleet.joined("b"):
            break
    assert fleet.joined_at["b"] == 2                        # the newest of its places the closures name
    assert fleet.placed_at["b"] == 32 and fleet.placed_at["b"] - first <= 2
    assert fleet.placed_at["a"] == 0
    restored = FleetMap.restore(fleet.params, fleet.consistency, fleet.state())
    assert restored.placed_at == fleet.placed_at and restored.latest == fleet.latest


def test_frame_placements_take_the_maps_own_record_over_a_stale_map_pose():
    from services.fleetmap.catchup import FramePlacements
    asked = []
    record = {f: (f // 2, (0.5 * (f % 2), 0.0, 0.0)) for f in range(20)}   # the map's own: an experience a 2 frames

    def ask(first, last):
        asked.append((first, last))
        return [(f, *record[f]) for f in range(first, last + 1)]

    frames = FramePlacements(kept=8, retry=3.0, patience=30.0)
    for f in range(10):   # map/pose offsets against experience poses published late: 0.25 m off
        frames.pose(f, f // 2, (0.5 * (f % 2) - 0.071, -0.229, 0.0))
    assert frames.find(10, ask, now=0.0) is None and not asked   # not posed yet: wait
    assert frames.find(4, ask, now=0.0) == record[4] and asked == [(4, 9)]
    assert frames.find(7, ask, now=0.0) == record[7] and asked == [(4, 9)]   # kept from the one answer
    assert len(frames.posed) == 8 and len(frames.placed) <= 8
    silent = FramePlacements(kept=8, retry=3.0, patience=30.0)
    for f in range(10):
        silent.pose(f, f // 2, (0.1, 0.0, 0.0))
    calls = []
    assert silent.find(5, lambda *span: calls.append(span), now=0.0) is None        # no answer: wait
    assert silent.find(5, lambda *span: calls.append(span), now=1.0) is None and len(calls) == 1   # asked again ...
    assert silent.find(5, lambda *span: calls.append(span), now=3.0) is None and len(calls) == 2   # ... after `retry`
    assert silent.find(6, ask, now=6.0) == record[6]   # it answers: its record
    assert silent.find(5, lambda *span: None, now=10.0) is None
    assert silent.find(5, lambda *span: None, now=40.0) == (2, (0.1, 0.0, 0.0))   # silent for `patience`: map/pose's


def test_a_robots_fleet_pose_is_placed_by_its_maps_own_placement_of_the_frame(tmp_path):
    """map/pose and map/update are on different keys, so the update that moved an experience may
    come after the pose of a frame at it: the fleet pose is placed by the frame's placement the
    map/pose carries, not by the pose against the experience's pose as last heard."""
    from schemas import Experience, FramePlacement, Header, Link, MapPose, MapUpdate, Time
    from services.common.convert import planar_pose
    from services.common.runtime import RuntimeConfig
    from services.fleetmap.service import FleetMapConfig, FleetMapService

    service = FleetMapService(RuntimeConfig(), FleetMapConfig(store=tmp_path / "fleet_map.log"))
    sent = []
    service._send = lambda topic, message: sent.append(message)   # the adapter's output, not a session
    service._publish_update = lambda force=False: None
    service._maybe_sync = lambda: None

    def head(seq):
        return Header(seq=seq, stamp=Time.from_seconds(seq * 0.1), frame_id="map", robot="a")

    link = Link(source=0, target=1, dx=1.0, dy=0.0, dheading=0.0, frame=1, covariance=[1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-6])
    service.on_map_update(MapUpdate(header=head(1), experiences=[Experience(id=0, x=0.0, y=0.0, heading=0.0, template_id=0, frame=0),
                                                                 Experience(id=1, x=1.0, y=0.0, heading=0.0, template_id=1, frame=1)],
                                    links=[link], experience_count=2, link_count=1))
    # The robot's map has since moved experience 1 to x = 1.3 (that map/update is still on its
    # way): its frame 5 is 0.2 m ahead of the experience, at x = 1.5 on the robot's map.
    placed = FramePlacement(frame=5, experience=1, dx=0.2, dy=0.0, dheading=0.0)
    for seq, placement in ((5, placed), (6, None)):
        sent.clear()
        service.on_map_pose(MapPose(header=head(seq), pose=planar_pose(1.5, 0.0, 0.0), heading=0.0, experience_id=1,
                                    placement=placement))
        (pose,) = sent
        expected = 1.2 if placement is not None else 1.5   # without it: the stale experience pose
        assert pose.pose.position.x == pytest.approx(expected, abs=1e-6), placement
        if placement is not None:   # a closure of that frame is placed by it too, without asking map/frames
            never = lambda first, last: pytest.fail("map/frames asked for a frame its map/pose placed")  # noqa: E731
            assert service.feeds["a"].frames.find(5, never, now=0.0) == (1, (0.2, 0.0, 0.0))
    # The same map/pose again (its expmap answering a re-sent frame with its kept outputs): no second fleet pose.
    sent.clear()
    service.on_map_pose(MapPose(header=head(6), pose=planar_pose(1.5, 0.0, 0.0), heading=0.0, experience_id=1))
    assert sent == []
