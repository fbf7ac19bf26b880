"""Inter-robot place recognition, a pure core (docs/fleet.md): a robot's frames matched against
the places other robots stored, learnt from them as keyframes (features and stereo depths, never
images), and confirmed as inter-robot loop closures by the paper's rule and measured by the same
closure geometry as the robot's own.

The other robots' places are kept apart from the robot's own: their bags of words (bow.py) in an
inverted index of their own, their keyframes in a store of their own, by a local index in the
order they arrived. Per frame (`observe`), the `candidates` best-scoring of them are verified
geometrically against the frame's features (ClosureGeometry.verify: a fundamental matrix's
inliers); each other robot's verified places are that robot's possible closures, of which the one
that continues the longest run of its consistency rule is the frame's vote for that robot, and it
is measured at once (ClosureGeometry.relative_pose: stereo PnP against the place's 3D points).
One ConsistencyRule per other robot confirms closures exactly as consistency.py does for the
robot's own places (more than six consistent votes in ten frames, the run's earlier votes
confirmed with it). The rule skips places stored fewer than `recent_frames` frames ago, which
says nothing across robots (their frame numbers are unrelated): another robot's frames are
numbered OTHER_BASE below every frame of this robot's, so none is recent and the offsets of a run
still agree.

Another robot's place can arrive after this robot saw it too: two robots driving side by side
each pass a place before the other's place of it arrives. So each frame is matched a second
time, `late_frames` frames after it was seen, against the places that arrived in between only
(its *late* votes, under a consistency rule of their own per robot, in the frames' order): a
place arriving up to that many frames late still closes the loop, and no frame is matched
twice against one place. A restarted service has not kept the features of the frames before
the restart (the journal holds none), so those get no late match.

What a frame did is its votes (`FleetVote`, journaled by the service: the frame's own and the
late votes of the frame `late_frames` before it); `replay` rebuilds the rules and the numbering
of the confirmed closures from them, so a restarted service confirms exactly what the
uninterrupted one did. Places already known are not added again (`add`): a
place re-sent after a restart or a partition is learnt once.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from services.common.frames import Camera
from services.common.settings import check, setting
from services.loopclosure.bow import BagVector, InvertedIndex, _best, bag_of
from services.loopclosure.consistency import ConsistencyParams, ConsistencyRule
from services.loopclosure.detector import Measurement
from services.loopclosure.geometry import ClosureGeometry, Features, Keyframe

OTHER_BASE = 10 ** 15   # another robot's frames, for the rule, are this far below this robot's


@dataclass(frozen=True)
class FleetParams:
    LABEL = "fleet place recognition"

    candidates: int = setting(4, ge=1, help="Other robots' places verified per frame (the best-scoring).")
    min_inliers: int = setting(30, ge=8, help="Matches fitting one camera motion for another robot's place to be a vote.")
    window: int = setting(10, ge=1, help="Consecutive frames of the inter-robot consistency rule.")
    min_votes: int = setting(7, ge=1, help="Consistent votes for one robot's places within the window to confirm a closure.")
    tolerance: int = setting(6, ge=0, help="Frames by which the votes' frame offsets may disagree.")
    late_frames: int = setting(20, ge=0, help="Frames after which a frame is matched again, against the places of other "
                               "robots that arrived since (0: never): places of a robot driving beside this one arrive "
                               "after this one saw them.")

    def check(self) -> None:
        check(self)
        ConsistencyParams(window=self.window, min_votes=self.min_votes, tolerance=self.tolerance).check()

    def consistency(self) -> ConsistencyParams:
        return ConsistencyParams(window=self.window, min_votes=self.min_votes, tolerance=self.tolerance,
                                 recent_frames=1, confirm_run=True)


@dataclass(frozen=True)
class FleetVote:
    """A frame's possible closure to another robot's place, measured."""

    robot: str
    place: int
    matched_frame: int          # the other robot's frame at which the place was stored
    measurement: Measurement


@dataclass(frozen=True)
class FleetConfirmed:
    """An inter-robot closure the rule confirmed: this robot's ``frame`` revisits ``robot``'s ``place``."""

    index: int
    frame: int
    robot: str
    place: int
    matched_frame: int
    votes: int
    measurement: Measurement


@dataclass(frozen=True)
class FleetObservation:
    """What one frame did: its own votes (one per robot at most), the late votes of the frames
    matched again now (frame, votes), and the closures confirmed."""

    votes: tuple[FleetVote, ...]
    late: tuple[tuple[int, tuple[FleetVote, ...]], ...]
    confirmed: tuple[FleetConfirmed, ...]


@dataclass(frozen=True)
class _Seen:
    """A frame waiting for its late match: its features and their bag of words (None: not made
    yet), and how many places were known then."""

    frame: int
    features: Features
    bag: BagVector | None
    camera: Camera | None
    known: int


class FleetRecognition:
    """Other robots' places, and the rules that confirm closures to them."""

    def __init__(self, vocabulary, params: FleetParams, geometry: ClosureGeometry, keyframes):
        """``keyframes``: where the other robots' keyframes are kept, by local index (a
        KeyframeStore or detector.MemoryKeyframes)."""
        params.check()
        self.vocabulary = vocabulary
        self.params = params
        self.geometry = geometry
        self.keyframes = keyframes
        self.index = InvertedIndex(vocabulary.words)
        self.places: list[tuple[str, int, int]] = []   # local index → (robot, place, frame)
        self._local: dict[tuple[str, int], int] = {}   # (robot, place) → local index
        self._known: dict[str, set[int]] = {}           # robot → its place ids learnt
        # per (robot, late): the rule, and the votes of its window by frame
        self.rules: dict[tuple[str, bool], ConsistencyRule] = {}
        self._measured: dict[tuple[str, bool], dict[int, FleetVote]] = {}
        self._seen: deque[_Seen] = deque()              # frames waiting for their late match, oldest first
        self.confirmed: list[FleetConfirmed] = []

    def __len__(self) -> int:
        return len(self.places)

    def known(self, robot: str) -> set[int]:
        """The place ids of ``robot`` learnt so far."""
        return self._known.get(robot, set())

    def next_missing(self, robot: str) -> int:
        """The lowest place id of ``robot`` not learnt yet."""
        known = self.known(robot)
        missing = 0
        while missing in known:
            missing += 1
        return missing

    def add(self, robot: str, place: int, frame: int, keyframe: Keyframe, store: bool = True) -> bool:
        """Learn another robot's place; False when it is known already. ``store``: keep its
        keyframe (False when replaying a store that holds it)."""
        if (robot, place) in self._local:
            return False
        local = len(self.places)
        if store:
            self.keyframes.append(local, keyframe)
        self.index.add(local, bag_of(self.vocabulary, keyframe.descriptors))
        self.places.append((robot, place, frame))
        self._local[(robot, place)] = local
        self._known.setdefault(robot, set()).add(place)
        return True

    def observe(self, seq: int, features: Features, camera: Camera | None = None) -> FleetObservation:
        """Match one frame (its features; ``camera`` for the measurement, default the places')
        against the other robots' places, and match again the frames seen `late_frames` before
        it against the places that arrived since."""
        bag = self._bag(features) if self.places else None
        votes = self._votes(seq, features, bag, camera, 0, late=False)
        confirmed = list(self._confirm(seq, votes, late=False))
        late = []
        if self.params.late_frames:
            self._seen.append(_Seen(seq, features, bag, camera, len(self.places)))
            while self._seen and self._seen[0].frame <= seq - self.params.late_frames:
                seen = self._seen.popleft()
                late_votes = self._votes(seen.frame, seen.features, seen.bag, seen.camera, seen.known, late=True)
                if late_votes:
                    late.append((seen.frame, late_votes))
                confirmed.extend(self._confirm(seen.frame, late_votes, late=True))
        return FleetObservation(votes, tuple(late), tuple(confirmed))

    def replay(self, seq: int, votes: tuple[FleetVote, ...], late: tuple[tuple[int, tuple[FleetVote, ...]], ...] = ()
               ) -> tuple[FleetConfirmed, ...]:
        """What a journaled frame confirmed, from its votes and late votes (as `observe` did)."""
        confirmed = list(self._confirm(seq, votes, late=False))
        for frame, late_votes in late:
            confirmed.extend(self._confirm(frame, late_votes, late=True))
        return tuple(confirmed)

    def _bag(self, features: Features) -> BagVector | None:
        return bag_of(self.vocabulary, features.descriptors) if len(features) else None

    def _votes(self, seq: int, features: Features, bag: BagVector | None, camera, first: int, late: bool
               ) -> tuple[FleetVote, ...]:
        """The frame's votes for the places from local index ``first`` on, one per robot at most
        (``bag``: the features' bag of words, made here when None)."""
        if len(self.places) <= first or not len(features):
            return ()
        scores = self.index.scores(bag if bag is not None else self._bag(features), len(self.places))
        verified: dict[str, list[tuple[int, int, int]]] = {}   # robot → (inliers, place, frame)
        for local in (_best(scores[first:], self.params.candidates) + first).tolist():
            keyframe = self.keyframes.get(local)
            inliers = 0 if keyframe is None else self.geometry.verify(keyframe, features)
            if inliers >= self.params.min_inliers:
                robot, place, frame = self.places[local]
                verified.setdefault(robot, []).append((inliers, place, frame))
        votes = []
        for robot in sorted(verified):
            ranked = sorted(verified[robot], key=lambda v: (-v[0], v[1]))
            chosen = self._rule(robot, late).choose(seq, [(place, frame - OTHER_BASE) for _, place, frame in ranked])
            if chosen is None:
                continue
            place, shifted = chosen
            keyframe = self.keyframes.get(self._local[(robot, place)])
            votes.append(FleetVote(robot, place, shifted + OTHER_BASE, self._measure(keyframe, camera, features)))
        return tuple(votes)

    def _rule(self, robot: str, late: bool) -> ConsistencyRule:
        if (robot, late) not in self.rules:
            self.rules[(robot, late)] = ConsistencyRule(self.params.consistency())
            self._measured[(robot, late)] = {}
        return self.rules[(robot, late)]

    def _confirm(self, seq: int, votes: tuple[FleetVote, ...], late: bool) -> tuple[FleetConfirmed, ...]:
        confirmed = []
        for vote in votes:
            rule, measured = self._rule(vote.robot, late), self._measured[(vote.robot, late)]
            for frame in [f for f in measured if f <= seq - self.params.window]:
                del measured[frame]
            measured[seq] = vote
            closure = rule.update(seq, vote.place, False, vote.matched_frame - OTHER_BASE)
            if closure is None:
                continue
            for frame in sorted({v.frame for v in closure.earlier} | {seq}):
                run_vote = measured[frame]
                confirmed.append(FleetConfirmed(len(self.confirmed), frame, vote.robot, run_vote.place,
                                                run_vote.matched_frame, closure.votes, run_vote.measurement))
                self.confirmed.append(confirmed[-1])
        return tuple(confirmed)

    def _measure(self, keyframe: Keyframe | None, camera, features: Features) -> Measurement:
        if keyframe is None or (camera or keyframe.camera) is None:
            return Measurement("none", error="no keyframe or camera")
        pose = self.geometry.relative_pose(keyframe, None, camera, features)
        if not pose.ok:
            return Measurement("none", inliers=pose.inliers, error=pose.reason)
        return Measurement(pose.method, pose.forward, pose.left, pose.yaw,
                           tuple(float(v) for v in pose.covariance.ravel()), pose.inliers)


def vote_record(vote: FleetVote) -> dict:
    m = vote.measurement
    return {"robot": vote.robot, "place": vote.place, "matched_frame": vote.matched_frame,
            "measurement": {"method": m.method, "forward": m.forward, "left": m.left, "yaw": m.yaw,
                            "covariance": list(m.covariance), "inliers": m.inliers, "error": m.error}}


def vote_of(record: dict) -> FleetVote:
    m = record["measurement"]
    return FleetVote(record["robot"], int(record["place"]), int(record["matched_frame"]),
                     Measurement(m["method"], m["forward"], m["left"], m["yaw"], tuple(m["covariance"]), m["inliers"],
                                 m["error"]))

