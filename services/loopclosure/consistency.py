"""The paper's loop-closure rule (Lu et al., ROBIO 2016, Sec. IV): a match of the current view
against a stored, non-recent template is a *possible* loop closure; a closure is *confirmed*
when more than six possible closures occur within ten consecutive frames and they are
consistent — the matched templates advance together with the current frames, in the same
order, within a tolerance (a revisit replays the earlier stretch of the route). The votes counted
are the longest such run ending at the newest vote.

A confirmed run confirms every vote in it: the closure of the newest frame comes with the
closures of the run's earlier frames that were not confirmed yet (`Closure.earlier`; with
`confirm_run` off, only the newest frame's, as RatSLAM does). Without that, the first six frames
of every revisit could never be closures, which on a sparse recording (a frame every metre or
two) is a large part of each revisit.

A frame may bring several possible closures (a place recogniser that finds more than one
earlier visit of a place): it votes for the one that continues the longest run (`choose`)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from services.common.errors import ConfigError
from services.common.settings import setting


@dataclass(frozen=True)
class ConsistencyParams:
    window: int = setting(10, ge=1, help="Consecutive frames of the consistency rule (the paper's ten).")
    min_votes: int = setting(7, ge=1, help="Consistent possible closures needed in the window (paper: more than six).")
    # A template spans several frames, and a robot that stops at a revisited place votes for one
    # place while its frames advance (seven votes in a row then span offsets six frames apart).
    tolerance: int = setting(6, ge=0, help="Frames by which the votes' frame offsets may disagree (min_votes − 1: "
                                           "a robot that stops at a revisited place).")
    recent_frames: int = setting(30, ge=1, help="Templates stored fewer frames ago are not loop closures.")
    confirm_run: bool = setting(True, help="A confirmed run of votes confirms the closures of its earlier frames too "
                                           "(false: only the newest frame's, as RatSLAM).")

    def check(self) -> None:
        for name, ok in (("window", self.window >= 1), ("min_votes", 1 <= self.min_votes <= self.window),
                         ("tolerance", self.tolerance >= 0), ("recent_frames", self.recent_frames >= 1)):
            if not ok:
                raise ConfigError(f"loop-closure consistency: invalid {name} = {getattr(self, name)!r}")


@dataclass(frozen=True)
class Vote:
    """A possible closure: ``frame`` looks like the place stored at ``matched_frame`` as ``template``."""

    frame: int
    matched_frame: int
    template: int


@dataclass(frozen=True)
class Closure:
    frame: int
    matched_frame: int
    matched_template: int
    votes: int
    earlier: tuple[Vote, ...] = ()   # earlier votes of the run, confirmed with it (oldest first)


class ConsistencyRule:
    """Feed every frame's view match in frame order; returns a Closure when one is confirmed."""

    def __init__(self, params: ConsistencyParams = ConsistencyParams()):
        params.check()
        self.params = params
        self.possible: deque[Vote] = deque()   # the votes of the window's frames
        self.confirmed: deque[int] = deque()   # frames of the window already confirmed

    def update(self, frame: int, template_id: int, is_new: bool, matched_frame: int) -> Closure | None:
        """One frame's match: a possible closure unless ``is_new`` or recent."""
        p = self.params
        while self.possible and self.possible[0].frame <= frame - p.window:
            self.possible.popleft()
        while self.confirmed and self.confirmed[0] <= frame - p.window:
            self.confirmed.popleft()
        if is_new or frame - matched_frame < p.recent_frames:
            return None
        vote = Vote(frame, matched_frame, template_id)
        run = self.run_to(vote)
        self.possible.append(vote)
        if len(run) < p.min_votes:
            return None
        earlier = tuple(v for v in run[:-1] if v.frame not in self.confirmed) if p.confirm_run else ()
        self.confirmed.extend(sorted({v.frame for v in earlier} | {frame}))
        return Closure(frame, matched_frame, template_id, len(run), earlier)

    def choose(self, frame: int, votes) -> tuple[int, int] | None:
        """Of a frame's possible closures, (template, matched frame) pairs best first (a place
        recogniser may find several earlier visits of one place), the one that continues the
        longest run of the window (the first of those); None when none is old enough."""
        best, longest = None, 0
        for template, matched in votes:
            if frame - matched < self.params.recent_frames:
                continue
            length = len(self.run_to(Vote(frame, matched, template)))
            if length > longest:
                best, longest = (template, matched), length
        return best

    def run_to(self, newest: Vote) -> list[Vote]:
        """The longest run of votes that agree with ``newest`` and ends at it, oldest first: frame
        offsets within the tolerance of the newest's (the matched frames advance with the current
        ones), matched frames in order (never going backwards), one vote per frame. The longest
        such run, not the first greedy one: an outlier early in the window (its offset inside the
        tolerance, its matched frame ahead of the others) must not hide the run that follows it."""
        offset = newest.frame - newest.matched_frame
        earlier = [v for v in self.possible if v.frame < newest.frame
                   and abs((v.frame - v.matched_frame) - offset) <= self.params.tolerance]
        # Longest chain ending at each vote (the window holds ten votes at most).
        longest: list[int] = []
        previous: list[int] = []
        for i, vote in enumerate(earlier):
            before = [j for j in range(i) if earlier[j].matched_frame <= vote.matched_frame]
            j = max(before, key=lambda j: longest[j], default=-1)
            longest.append(1 + (longest[j] if j >= 0 else 0))
            previous.append(j)
        ends = [j for j, v in enumerate(earlier) if v.matched_frame <= newest.matched_frame]
        j = max(ends, key=lambda j: longest[j], default=-1)
        run = [newest]
        while j >= 0:
            run.append(earlier[j])
            j = previous[j]
        return run[::-1]
