"""The fleet map's core (services/fleetmap/graph.py, consistency.py, store.py): two robots' maps
on one loop, joined by consistent inter-robot closures, look-alike closures refused or split
away, and a journal that rebuilds the same map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.expmap.graph import between
from services.fleetmap.consistency import Candidate, ConsistencyParams, consistency_graph, maximum_clique
from services.fleetmap.graph import ClosureInput, FleetMap, FleetParams
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


def test_a_span_longer_than_the_look_alikes_keeps_them_from_joining(two):
    _, truth_a, truth_b = two
    fleet = FleetMap(FleetParams(frame_robot="a", join_span=8.0))
    for name, (truth, e, links) in (("a", robot(0)), ("b", robot(40))):
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
