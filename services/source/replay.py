"""The source's frames in flight: the window, the acknowledgements and the resends.

Offline replay loses nothing: the source keeps at most `limit` frames in flight (sent, not yet
acknowledged by the pipeline's last stage) and counts a frame done when an acknowledgement of it
or of a later frame arrives (cumulative). With an AdaptiveWindow (window.py) the limit follows
the pipeline; otherwise it is the configured window (0: no flow control, nothing is tracked).

Frames in flight are sent again:

- when no acknowledgement came for `resend_after` s (a service restarted downstream lost them;
  services that already handled a frame replay their outputs instead of computing them again),
- `reconnect_settle` s after camera/frame regained a subscriber, having lost them all after the
  first frame (the router came back: what was in flight is lost with it). Every client rejoins
  within its retry period (runtime.py: at most 0.5 s), so the re-sent frames find all consumers
  back, not only the first one to reconnect.

A resend leads with the last `resend_acknowledged` acknowledged frames, oldest first: every stage
has handled them (they replay their outputs), and an estimator restarted downstream runs its
block again from them, so the frames in flight get the increments an uninterrupted run gives
them. A live camera's old frames are worth nothing: its frames in flight are given up instead,
to make room for the newest.

Also here: `Pacer`, the source's frame rate. Pure: every time is an argument (seconds on one
monotonic clock), and a frame is opaque here.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Any

from services.source.window import AdaptiveWindow

STALL_LOG_PERIOD_S = 10.0   # how often a source stalled on its window says so


@dataclass(frozen=True)
class ReplayParams:
    window: int = 8                  # most frames in flight; 0: no flow control
    live: bool = False               # a live camera: give up frames in flight instead of re-sending them
    resend_after: float = 5.0        # s without an acknowledgement before the frames in flight go again
    resend_acknowledged: int = 17    # acknowledged frames sent again before them
    reconnect_settle: float = 0.5    # s after camera/frame has subscribers again before they go again


@dataclass(frozen=True)
class Resend:
    """Frames in flight to deal with again: `frames` to send again, in order (the last
    acknowledged ones first), or, from a live camera, `abandoned` frames given up."""

    reason: str
    frames: tuple[Any, ...] = ()
    abandoned: int = 0
    first: int | None = None   # the oldest frame in flight's seq
    in_flight: int = 0


@dataclass
class ReplayController:
    """Fed with every frame sent (`sent`), every acknowledgement (`acked`), camera/frame's
    subscribers (`subscribers`); asked whether the window is `full` and whether frames are due
    to go again (`resend_due`)."""

    params: ReplayParams = ReplayParams()
    flow: AdaptiveWindow | None = None
    in_flight: collections.OrderedDict[int, Any] = field(default_factory=collections.OrderedDict)
    frames_sent: int = 0
    resent: int = 0      # frames in flight sent again
    abandoned: int = 0   # live: frames in flight given up
    last_progress: float = 0.0                  # when a frame in flight was last acknowledged (or sent again)
    unreachable: bool = False                   # camera/frame lost every subscriber after the first frame
    reconnected_at: float | None = None         # when it regained one
    stalled_since: float | None = None          # when the window was found full, while it stays full

    def __post_init__(self):
        self.acknowledged: collections.deque[Any] = collections.deque(maxlen=self.params.resend_acknowledged)

    @property
    def limit(self) -> int:
        """Frames in flight before the source waits (0: no flow control)."""
        return self.flow.limit if self.flow is not None else self.params.window

    @property
    def full(self) -> bool:
        """The window holds as many frames as it may: the next one waits."""
        return bool(self.params.window) and len(self.in_flight) >= self.limit

    @property
    def settled(self) -> bool:
        """Nothing awaits an acknowledgement (or nothing is tracked: no flow control)."""
        return not self.in_flight or not self.params.window

    @property
    def oldest(self) -> int | None:
        """The seq of the oldest frame in flight."""
        return next(iter(self.in_flight), None)

    def sent(self, seq: int, frame: Any, now: float) -> None:
        """A new frame went out."""
        self.frames_sent += 1
        if not self.params.window:
            return
        if not self.in_flight:
            self.last_progress = now
        self.in_flight[seq] = frame
        if self.flow is not None:
            self.flow.sent(seq, now)

    def acked(self, seq: int, now: float) -> None:
        """Every frame up to `seq` has come through the pipeline."""
        while self.in_flight and next(iter(self.in_flight)) <= seq:
            self.acknowledged.append(self.in_flight.popitem(last=False)[1])
            self.last_progress = now
        if self.flow is not None:
            self.flow.acked(seq, now)

    def subscribers(self, matching: bool, now: float) -> None:
        """camera/frame has subscribers (`matching`) or has none (called on a transport thread)."""
        if not matching:
            self.unreachable = self.frames_sent > 0
        elif self.unreachable:
            self.unreachable = False
            self.reconnected_at = now

    def resend_due(self, now: float) -> Resend | None:
        """The frames in flight to send again (or give up) now, if they are due; once the frames
        to send again are out, `resend_done`."""
        if self.reconnected_at is not None and now - self.reconnected_at >= self.params.reconnect_settle:
            self.reconnected_at = None
            if self.in_flight:
                return self._resend("camera/frame has subscribers again", now)
        if self.in_flight and now - self.last_progress > self.params.resend_after:
            return self._resend(f"no acknowledgement for {self.params.resend_after:.1f} s", now)
        return None

    def resend_done(self, now: float) -> None:
        """The frames of a resend are out (sending them may have waited on the pipeline): the
        wait for an acknowledgement starts again."""
        self.last_progress = now

    def stalled(self, now: float) -> float | None:
        """The window is full: how long it has been, every STALL_LOG_PERIOD_S (else None)."""
        if self.stalled_since is None:
            self.stalled_since = now
        elif now - self.stalled_since >= STALL_LOG_PERIOD_S:
            waited, self.stalled_since = now - self.stalled_since, now
            return waited
        return None

    def moving(self) -> None:
        """The window has room again."""
        self.stalled_since = None

    def _resend(self, reason: str, now: float) -> Resend:
        first, count = self.oldest, len(self.in_flight)
        if self.params.live:
            self.abandoned += count
            self.in_flight.clear()
            self.last_progress = now
            return Resend(reason, abandoned=count, first=first, in_flight=count)
        frames = (*self.acknowledged, *self.in_flight.values())
        if self.flow is not None:
            self.flow.resent()
        self.resent += count
        return Resend(reason, frames=frames, first=first, in_flight=count)


@dataclass
class Pacer:
    """Frames at `rate` a second (0: as fast as the window allows); after a stall, the frames
    of at most the last second go at once (rather than all those the stall held back), then the pace."""

    rate: float = 0.0
    next_due: float = 0.0

    def delay(self, now: float) -> float:
        """Seconds until the next frame may go (0: now, and its slot is taken)."""
        if self.rate <= 0:
            return 0.0
        if self.next_due - now > 0:
            return self.next_due - now
        self.next_due = max(self.next_due, now - 1.0) + 1.0 / self.rate
        return 0.0
