"""A saved map used again (services/expmap: graph.py's sessions and parts, localizer.py): a later
session is a part of its own until consistent closures join it; a localisation is placed by
consistent closures and keeps to the map; places the map knows to have a look-alike place
nothing; without closures a localisation is lost."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from services.common.geometry import between, compose, wrap
from services.common.layout import session_base
from services.expmap.graph import JOINED_PRIOR_SIGMA, ExperienceMap, MapParams
from services.expmap.links import ClosureInput
from services.expmap.store import MapStore, Step, sessions_of
from tests.unit.test_expmap import (
    CLOSURE_COVARIANCE,
    drive_square,
    least_squares,
    same_state,
    whole_graph_innovation,
)

PARAMS = MapParams(new_experience_distance=0.6)
B = session_base(1)
ROUTE = drive_square(side=8.0, laps=1.0)           # the map's lap: 129 frames, 0.25 m apart
TRUTH = {frame: pose for frame, pose, _, _ in ROUTE}
DRIVE = drive_square(side=8.0, laps=3.0)           # a later session goes on round the square
LOOK_ALIKE = range(100, 108)                       # side 3 of the map's lap looks like ...
LOOKED_AT = range(36, 44)                          # ... side 1, 8 m across the square


def saved_map(look_alike: bool = False) -> ExperienceMap:
    """The lap, mapped; with ``look_alike``, frames 100..107 bring closures measured as if they
    were at frames 36..43, which the map refuses (it then knows those places have look-alikes)."""
    experience_map = ExperienceMap(PARAMS)
    for frame, _, odometry, template in ROUTE:
        closure = None
        if look_alike and frame in LOOK_ALIKE:
            closure = ClosureInput(0, LOOKED_AT[frame - LOOK_ALIKE[0]], "stereo", 0.0, 0.0, 0.0, CLOSURE_COVARIANCE)
        experience_map.step(frame, odometry, template, closure)
    return experience_map


def closure_of(true_pose, frame: int, matched: int, seen_at=None) -> ClosureInput:
    """What the images measure between a session's frame (at ``true_pose``) and the map's frame
    ``matched`` (``seen_at``: the map frame it truly looks at, for a look-alike)."""
    seen_at = matched if seen_at is None else seen_at
    return ClosureInput(0, matched, "stereo", *between(TRUTH[seen_at], true_pose), CLOSURE_COVARIANCE, frame=frame)


def session(start: int, count: int, batches: dict[int, list[tuple[int, int]]]):
    """A session driving the route from the map's frame ``start`` on, its odometry from its own
    origin: (global frame, true pose, odometry, closures confirmed at it); ``batches``: at session
    frame k, closures (j, m) of session frame j to map frame m (a run the rule confirmed), each
    measured from what frame j truly sees (the map's frame start + j, one lap earlier)."""
    frames = []
    for k in range(count):
        true_pose = DRIVE[start + k][1]
        closures = [closure_of(DRIVE[start + j][1], B + j, matched, seen_at=(start + j) % 128)
                    for j, matched in batches.get(k, [])]
        frames.append((B + k, true_pose, between(DRIVE[start][1], true_pose), closures))
    return frames


def drive(experience_map: ExperienceMap, frames, first: int = 0) -> list:
    """Step the map through a session's frames (``first``: the session frame they start at)."""
    results = []
    for k, (frame, _, odometry, closures) in enumerate(frames, start=first):
        own = next((dataclasses.replace(c, frame=-1) for c in closures if c.frame == frame), None)
        earlier = tuple(c for c in closures if c.frame != frame)
        results.append(experience_map.step(frame, odometry, 1000 + k, own, None, earlier))
    return results


def true_batch(start: int, at: int) -> dict:
    """Closures of session frames at−6..at to the map frames they revisit."""
    return {at: [(j, start + j) for j in range(at - 6, at + 1)]}


def test_a_later_session_is_its_own_part_until_consistent_closures_join_it_into_the_map():
    experience_map = saved_map()
    saved = len(experience_map)
    experience_map.start_session()
    frames = session(40, 30, true_batch(40, 16))
    results = drive(experience_map, frames)
    assert not any(r.localized for r in results[:16]) and all(r.localized for r in results[16:])
    assert results[16].joined == [1] and experience_map.anchors == {0: 0} and set(experience_map.parts) == {0}
    assert len(experience_map) > saved
    assert [fate for _, fate, _ in results[16].decisions].count("accepted") == 7
    for result, (_, true_pose, _, _) in zip(results[16:], frames[16:]):   # in the saved map's frame now
        assert math.dist(result.pose[:2], true_pose[:2]) < 0.05


def drifting(frames, heading_drift: float):
    """The session's frames with odometry whose heading drifts by ``heading_drift`` rad a frame."""
    odometry, result = frames[0][2], []
    for k, (frame, true_pose, _, closures) in enumerate(frames):
        if k:
            dx, dy, dheading = between(frames[k - 1][1], true_pose)
            odometry = compose(odometry, (dx, dy, dheading + heading_drift))
        result.append((frame, true_pose, odometry, closures))
    return result


JOINED_SESSION = drifting(session(40, 51, {**true_batch(40, 16), **true_batch(40, 50)}), 0.002)


def test_a_joined_map_is_the_least_squares_solution_of_its_whole_graph_and_tests_closures_by_it():
    # The session (its heading drifting 2 mrad a frame) joined at its frame 16, its prior made
    # weak; closures again at frame 50. The map is its whole graph's solution, both parts' priors
    # in it (1.0 mm and 0.3 mrad from it; with every experience in the solver, 2.8 mm), and the
    # last closure's test statistic the whole graph's innovation (2.4 % off; with every experience
    # in the solver, 14 %).
    experience_map = saved_map()
    saved = len(experience_map)
    experience_map.start_session()
    results = drive(experience_map, JOINED_SESSION)
    assert results[16].joined == [1]
    assert [fate for _, fate, _ in results[50].decisions] == ["accepted"] * 7
    state = experience_map.state()
    assert state["part_priors"][:, [0, 4]].tolist() == [[saved, JOINED_PRIOR_SIGMA]]   # the session's first experience
    assert len(state["junctions"]) < len(experience_map) / 3
    poses = experience_map.final_poses()
    solution, _, _ = least_squares(experience_map, poses)
    assert poses[:, :2] == pytest.approx(solution[:, :2], abs=2e-3)
    assert np.abs(wrap(poses[:, 2] - solution[:, 2])).max() < 5e-4
    last = len(experience_map.links) - 1
    assert experience_map.links[last].loop_closure
    expected = whole_graph_innovation(experience_map, last)
    assert expected > 0.2   # the drift the closure corrects
    assert experience_map.residuals[-1] == pytest.approx(expected, rel=0.05)


def test_a_map_of_two_parts_restored_from_its_state_goes_on_bit_for_bit_as_the_rebased_one():
    # Rebased before the join (two parts, each with its prior), after it, and between closures.
    for split in (10, 17, 30):
        live = saved_map()
        live.start_session()
        drive(live, JOINED_SESSION[:split])
        restored = ExperienceMap.restore(PARAMS, {key: value.copy() for key, value in live.rebase().items()})
        assert len(live.anchors) == (2 if split <= 16 else 1)
        for k in range(split, len(JOINED_SESSION)):
            assert drive(restored, JOINED_SESSION[k:k + 1], k)[0].moved == drive(live, JOINED_SESSION[k:k + 1], k)[0].moved
        same_state(restored, live)


def test_closures_that_disagree_or_reach_places_with_look_alikes_join_nothing():
    # Seven closures each labelled with another place than the one seen: no three agree on where
    # the session is.
    experience_map = saved_map()
    experience_map.start_session()
    frames = session(40, 30, {16: [(j, 40 + j + 5 * (j - 10)) for j in range(10, 17)]})
    results = drive(experience_map, frames)
    assert not any(r.localized for r in results) and set(experience_map.parts) == {0, 1}
    assert [fate for _, fate, _ in results[16].decisions] == ["rejected"] * 7
    # A map that knows side 1 has a look-alike (side 3): a true run of closures to side 1 joins
    # nothing; the next run, on side 2, joins the session there.
    experience_map = saved_map(look_alike=True)
    experience_map.start_session()
    frames = session(28, 60, {**true_batch(28, 14), **true_batch(28, 50)})   # map frames 36..42, then 72..78
    results = drive(experience_map, frames)
    assert not any(r.localized for r in results[:50]) and all(r.localized for r in results[50:])
    assert math.dist(results[55].pose[:2], frames[55][1][:2]) < 0.05


def test_a_localisation_is_placed_by_consistent_closures_and_adds_nothing_to_the_map():
    experience_map = saved_map()
    experiences, links = len(experience_map), len(experience_map.links)
    experience_map.start_session(localize=True)
    frames = session(40, 40, {**true_batch(40, 16), 30: [(30, 70)]})
    results = drive(experience_map, frames)
    assert not any(r.localized for r in results[:16]) and all(r.localized for r in results[16:])
    assert results[15].pose == frames[15][2]   # not placed yet: the odometry's pose
    for result, (_, true_pose, _, _) in zip(results[16:], frames[16:]):
        assert math.dist(result.pose[:2], true_pose[:2]) < 0.05
    assert [fate for _, fate, _ in results[30].decisions] == ["accepted"]
    assert (len(experience_map), len(experience_map.links)) == (experiences, links)


def test_a_localisation_at_a_place_with_a_look_alike_waits_for_one_without_and_is_lost_without_closures():
    experience_map = saved_map(look_alike=True)
    experience_map.start_session(localize=True)
    # The session starts on side 3 (map frames 98..): its first run of closures, to the look-alike
    # stretch (frames 100..106), places nothing; the next, at frames 114..120, places it.
    frames = session(98, 150, {8: [(j, 98 + j) for j in range(2, 9)], **true_batch(98, 22)})
    results = drive(experience_map, frames)
    assert not any(r.localized for r in results[:22]) and results[22].placed
    assert all(math.dist(r.pose[:2], t[:2]) < 0.05 for r, (_, t, _, _) in zip(results[22:40], frames[22:40]))
    # No closure after it: lost once more than 30 m (120 frames of 0.25 m) are driven.
    assert results[142].localized and results[143].lost and not any(r.localized for r in results[143:])


def test_a_session_journal_replays_to_the_same_map(tmp_path):
    frames = session(40, 30, true_batch(40, 16))
    store = MapStore(tmp_path / "map.log", PARAMS)
    for frame, _, odometry, template in ROUTE:
        store.append(Step(frame, 0.1 * frame, odometry, template))
    store.journal.append({"session": 1, "localize": False, "map": "A"})
    for k, (frame, _, odometry, closures) in enumerate(frames):
        own = next((dataclasses.replace(c, frame=-1) for c in closures if c.frame == frame), None)
        store.append(Step(frame, 0.1 * k, odometry, 1000 + k, own, None, tuple(c for c in closures if c.frame != frame)))
    store.close()
    reopened = MapStore(tmp_path / "map.log", PARAMS)
    assert sessions_of(reopened.journal.records) == [(len(ROUTE), {"session": 1, "localize": False, "map": "A"})]
    rebuilt, _, _ = reopened.rebuild()
    live = saved_map()
    live.start_session()
    drive(live, frames)
    assert np.array_equal(rebuilt.poses, live.poses) and rebuilt.parts == live.parts and rebuilt.anchors == live.anchors
