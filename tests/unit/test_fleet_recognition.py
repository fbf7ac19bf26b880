"""Inter-robot place recognition (services/loopclosure/fleet.py) on real rendered views of the
synthetic world: another robot's places arriving after this robot passed them still close the
loop, `late_frames` frames after it saw them, and a journal's replay confirms the same closures."""

from __future__ import annotations

import pytest

from services.loopclosure.detector import MemoryKeyframes
from services.loopclosure.fleet import FleetParams, FleetRecognition, vote_of, vote_record
from services.loopclosure.geometry import ClosureGeometry
from services.loopclosure.vocabulary import default_vocabulary
from services.source.synthetic import SyntheticWorld, WorldConfig

GEOMETRY = ClosureGeometry()
PLACES = range(10, 42, 3)      # robot b's places: its views of these frames' stretch, on the second lap


@pytest.fixture(scope="module")
def world():
    return SyntheticWorld(WorldConfig(seed=0))


@pytest.fixture(scope="module")
def views(world):
    """Robot a's features of its frames 0–71: lap-1 frames 0–41, then 120–149 (a stretch b never
    saw), and b's keyframes of the lap-2 views of PLACES."""
    own = {seq: GEOMETRY.features(world[f].left) for seq, f in enumerate([*range(42), *range(120, 150)])}
    lap = world.frames_per_lap
    places = [(i, lap + f, GEOMETRY.keyframe(world[lap + f].left, world[lap + f].right, world[lap + f].camera))
              for i, f in enumerate(PLACES)]
    return own, places, world[0].camera


def drive(views, late_frames: int):
    """Robot a drives its frames 0–41, b's places arrive, a drives on: its recognition and what
    each frame did."""
    own, places, camera = views
    recognition = FleetRecognition(default_vocabulary(), FleetParams(late_frames=late_frames), GEOMETRY, MemoryKeyframes())
    seen = {}
    for frame in own:
        if frame == 42:
            for place, place_frame, keyframe in places:
                assert recognition.add("b", place, place_frame, keyframe)
        seen[frame] = recognition.observe(frame, own[frame], camera)
    return recognition, seen


def test_places_arriving_after_the_robot_passed_them_close_the_loop_late(views, world):
    _, seen = drive(views, late_frames=0)
    assert not any(s.confirmed or s.votes or s.late for s in seen.values())
    recognition, seen = drive(views, late_frames=20)
    confirmed = recognition.confirmed
    # frames 22–41 were still waiting for their late match when the places came
    assert len(confirmed) >= 10 and all(22 <= c.frame <= 41 for c in confirmed)
    lap = world.frames_per_lap
    assert all(c.robot == "b" and abs(c.matched_frame - lap - c.frame) <= 6 for c in confirmed)
    assert [c.index for c in confirmed] == list(range(len(confirmed)))
    measured = [c for c in confirmed if c.measurement.method == "stereo"]
    assert len(measured) >= len(confirmed) - 2
    for c in measured:   # a's frame ahead of b's place by the frames between them along the route
        assert abs(c.measurement.forward - world.speed * (c.frame - (c.matched_frame - lap))) < 0.05
        assert abs(c.measurement.left) < 0.15
    # the frames matched late are the 20 before each frame, and only against places newer than them
    assert all(frame == seq - 20 for seq, s in seen.items() for frame, _ in s.late)
    assert not any(s.votes for s in seen.values())


def test_a_replay_of_the_journaled_votes_confirms_the_same_closures(views):
    recognition, seen = drive(views, late_frames=20)
    replayed = FleetRecognition(default_vocabulary(), FleetParams(late_frames=20), GEOMETRY, MemoryKeyframes())
    for frame, s in seen.items():   # through the journal's records
        votes = tuple(vote_of(vote_record(v)) for v in s.votes)
        late = tuple((f, tuple(vote_of(vote_record(v)) for v in vs)) for f, vs in s.late)
        assert replayed.replay(frame, votes, late) == s.confirmed
    assert replayed.confirmed == recognition.confirmed and recognition.confirmed


def test_late_frames_is_checked():
    with pytest.raises(Exception, match="late_frames"):
        FleetParams(late_frames=-1).check()

