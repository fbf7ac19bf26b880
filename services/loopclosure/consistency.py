"""The paper's loop-closure rule (Lu et al., ROBIO 2016, Sec. IV): a match of the current view
against a stored, non-recent template is a *possible* loop closure; a closure is *confirmed*
when more than six possible closures occur within ten consecutive frames and they are
consistent — the matched templates advance together with the current frames, in the same
order, within a tolerance (a revisit replays the earlier stretch of the route). The votes counted
are the longest such run ending at the newest vote."""

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

    def check(self) -> None:
        for name, ok in (("window", self.window >= 1), ("min_votes", 1 <= self.min_votes <= self.window),
                         ("tolerance", self.tolerance >= 0), ("recent_frames", self.recent_frames >= 1)):
            if not ok:
                raise ConfigError(f"loop-closure consistency: invalid {name} = {getattr(self, name)!r}")


@dataclass(frozen=True)
class Closure:
    frame: int
    matched_frame: int
    matched_template: int
    votes: int


class ConsistencyRule:
    """Feed every frame's view match in frame order; returns a Closure when one is confirmed."""

    def __init__(self, params: ConsistencyParams = ConsistencyParams()):
        params.check()
        self.params = params
        self.possible: deque[tuple[int, int, int]] = deque()   # (frame, matched_frame, template) in the window

    def update(self, frame: int, template_id: int, is_new: bool, matched_frame: int) -> Closure | None:
        p = self.params
        while self.possible and self.possible[0][0] <= frame - p.window:
            self.possible.popleft()
        if is_new or frame - matched_frame < p.recent_frames:
            return None
        self.possible.append((frame, matched_frame, template_id))
        votes = self.consistent_votes()
        if votes < p.min_votes:
            return None
        return Closure(frame, matched_frame, template_id, votes)

    def consistent_votes(self) -> int:
        """The longest run of votes that agree with the newest one and ends at it: frame offsets
        within the tolerance of the newest's (the matched frames advance with the current ones),
        matched frames in order (never going backwards). The longest such run, not the first
        greedy one: an outlier early in the window (its offset inside the tolerance, its matched
        frame ahead of the others) must not hide the run that follows it."""
        frame, matched, _ = self.possible[-1]
        offset = frame - matched
        agreeing = [vote_matched for vote_frame, vote_matched, _ in self.possible
                    if abs((vote_frame - vote_matched) - offset) <= self.params.tolerance]
        # Longest non-decreasing subsequence ending at each vote (the window holds ten at most).
        longest: list[int] = []
        for i, current in enumerate(agreeing):
            longest.append(1 + max((longest[j] for j in range(i) if agreeing[j] <= current), default=0))
        return longest[-1]
