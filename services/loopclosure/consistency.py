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
earlier visit of a place: `update_votes`); at most one of them counts in a run."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from services.common.errors import ConfigError


@dataclass(frozen=True)
class ConsistencyParams:
    window: int = 10            # consecutive frames considered (the paper's ten)
    min_votes: int = 7          # possible closures needed within the window ("more than six")
    tolerance: int = 5          # frames by which a vote's frame offset may differ (a template spans several frames)
    recent_frames: int = 30     # a template stored fewer frames ago than this is not a loop closure
    confirm_run: bool = True    # a confirmed run confirms its earlier votes too (else only the newest)

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
        return self.update_votes(frame, () if is_new else ((template_id, matched_frame),))

    def update_votes(self, frame: int, votes) -> Closure | None:
        """One frame's possible closures, (template, matched frame) pairs, best first; the first
        of those with the longest run wins."""
        p = self.params
        while self.possible and self.possible[0].frame <= frame - p.window:
            self.possible.popleft()
        while self.confirmed and self.confirmed[0] <= frame - p.window:
            self.confirmed.popleft()
        candidates = [Vote(frame, matched, template) for template, matched in votes if frame - matched >= p.recent_frames]
        best: list[Vote] = []
        for vote in candidates:
            run = self.run_to(vote)
            if len(run) > len(best):
                best = run
        self.possible.extend(candidates)
        if len(best) < p.min_votes:
            return None
        newest = best[-1]
        earlier = tuple(v for v in best[:-1] if v.frame not in self.confirmed) if p.confirm_run else ()
        self.confirmed.extend(sorted({v.frame for v in earlier} | {frame}))
        return Closure(frame, newest.matched_frame, newest.template, len(best), earlier)

    def consistent_votes(self) -> int:
        """The length of the run ending at the window's newest vote (`run_to`)."""
        return len(self.run_to(self.possible[-1]))

    def run_to(self, newest: Vote) -> list[Vote]:
        """The longest run of votes that agree with ``newest`` and ends at it, oldest first: frame
        offsets within the tolerance of the newest's (the matched frames advance with the current
        ones), matched frames in order (never going backwards), one vote per frame. The longest
        such run, not the first greedy one: an outlier early in the window (its offset inside the
        tolerance, its matched frame ahead of the others) must not hide the run that follows it."""
        offset = newest.frame - newest.matched_frame
        earlier = [v for v in self.possible if v.frame < newest.frame
                   and abs((v.frame - v.matched_frame) - offset) <= self.params.tolerance]
        # Longest chain ending at each vote (the window holds ten frames, a few votes each).
        longest: list[int] = []
        previous: list[int] = []
        for i, vote in enumerate(earlier):
            before = [j for j in range(i) if earlier[j].frame < vote.frame and earlier[j].matched_frame <= vote.matched_frame]
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
