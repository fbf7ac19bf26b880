"""The order in which a service handles its messages: by `seq`, with gaps and stale frames named.

Each subscription of a service is one stream of the `Sequencer`. A message offered to it is
delivered at once, or held until the message it follows has been delivered, then delivered in
order; each delivery says how many frames went missing before it and whether it is stale (at or
before the last one delivered: a frame sent again). Two waits hold messages:

- A message that names the one it follows (EgoMotion.previous_seq: several egomotion instances
  publish out of order) waits for it up to `order_wait` s (`order_wait_first` before the stream's
  first delivery: a service started mid-run), then the held messages go on with a gap.
- After the link to the router came back (`reconnected`), a frame of an ordered stream that
  skips ahead of the last one delivered waits up to `recovery` s for the ones between (lost with
  the router, sent again by the source): frames are still handled in order. A gap that is real
  (a skipped file, a live camera's drops) ends the wait; so do more than `max_held` frames held.

Pure: every time is an argument (seconds on one monotonic clock); nothing here reads a clock,
and what a message is does not matter here (its seq, the seq it follows and an opaque item).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SequencerParams:
    order_wait: float = 20.0        # s a message waits for the one it follows
    order_wait_first: float = 2.0   # ... before the stream's first delivery
    recovery: float = 5.0           # s after a reconnection during which frames that skip ahead wait
    max_held: int = 256             # messages held per stream, beyond which the wait ends early


@dataclass
class SeqTracker:
    """Detects gaps and stale (duplicate or out-of-order) `seq` numbers on one stream."""

    last: int | None = None

    def check(self, seq: int, stride: int = 1) -> tuple[int, bool]:
        """(frames missing before `seq`, whether `seq` is stale); the stream's frames are `stride`
        apart (Header.stride: a frame skipped on purpose is no gap)."""
        if self.last is not None and seq <= self.last:
            return 0, True
        missing = 0 if self.last is None else -(-(seq - self.last) // stride) - 1
        self.last = seq
        return missing, False


@dataclass(frozen=True)
class Delivery:
    """What to do with one message now: handle it (`stale`: it is at or before the last one
    delivered; `missing`: frames lost before it), or, `duplicate`, drop it: it came again while
    held (once is enough)."""

    stream: int
    seq: int
    item: Any
    missing: int = 0
    stale: bool = False
    duplicate: bool = False


@dataclass
class _Stream:
    name: str
    ordered: bool    # every frame expected, in order: frames that skip ahead wait after a reconnection
    follows: bool    # its messages name the seq they follow
    seq: SeqTracker = field(default_factory=SeqTracker)
    held: dict[int, tuple[int | None, Any]] = field(default_factory=dict)   # seq → (previous, item)
    held_since: float | None = None   # when the wait for a `follows` link began
    stride: int = 1   # seqs between two frames of the stream (Header.stride), as its last message said

    def follows_on(self, seq: int, previous: int | None) -> bool:
        """Whether a message may be delivered now: the frame it comes after has been."""
        last = self.seq.last
        if not self.follows:
            return last is None or seq <= last + self.stride
        return previous is None or (last is not None and previous <= last)


class Sequencer:
    """The streams of one service (`stream()`), fed with every message (`offer()`) and polled
    with the time (`due()`, the waits that ended); `reconnected()` begins a recovery wait."""

    def __init__(self, params: SequencerParams = SequencerParams(), name: str = "service"):
        self.params = params
        self.name = name   # the service, for log lines
        self._streams: list[_Stream] = []
        self._recovering_until: float | None = None

    def stream(self, name: str, *, ordered: bool, follows: bool = False, handled_up_to: int | None = None) -> int:
        """A new stream (`name`: its topic, for log lines), its index. `handled_up_to`: the last
        seq a previous process handled (it resumed from a checkpoint): messages up to it are stale."""
        self._streams.append(_Stream(name, ordered, follows, SeqTracker(handled_up_to)))
        return len(self._streams) - 1

    def last(self, stream: int) -> int | None:
        """The last seq delivered on `stream` (None: none yet)."""
        return self._streams[stream].seq.last

    def held(self, stream: int) -> list[int]:
        """The seqs held on `stream`, in order."""
        return sorted(self._streams[stream].held)

    @property
    def recovering(self) -> bool:
        return self._recovering_until is not None

    def reconnected(self, now: float) -> None:
        """The link to the router is back: frames that skip ahead wait `recovery` s for the ones between."""
        self._recovering_until = now + self.params.recovery

    def offer(self, stream: int, seq: int, previous: int | None, item: Any, now: float,
              key: str | None = None, stride: int = 1) -> list[Delivery]:
        """A message arrived (`previous`: the seq it follows, where its stream's messages name
        one; `key`: where it came from, for log lines; `stride`: its Header.stride): what to
        deliver now, in order."""
        s = self._streams[stream]
        s.stride = stride
        last = s.seq.last
        if s.follows:
            if not (s.follows_on(seq, previous) or (last is not None and seq <= last)):
                return self._hold(stream, s, seq, previous, item, now)
        elif self._recovering_until is not None and s.ordered and last is not None and seq > last + stride:
            # Frames lost with the router come again after this one: it waits for them.
            if not s.held:
                log.warning("%s: seq %d follows %d on %s after a reconnection; waiting up to %.0f s for the frames between",
                            self.name, seq, last, key or s.name, self.params.recovery)
            if seq in s.held:
                return [Delivery(stream, seq, item, duplicate=True)]
            s.held[seq] = (previous, item)
            if len(s.held) > self.params.max_held:
                return self._end_recovery()
            return []
        return [self._deliver(stream, s, seq, item), *self._release(stream, s)]

    def due(self, now: float) -> list[Delivery]:
        """The messages whose wait ended by `now` (the recovery's time is up; a link waited for
        too long), in the order to deliver them."""
        out = []
        if self._recovering_until is not None and now > self._recovering_until:
            out += self._end_recovery()
        for index, s in enumerate(self._streams):
            if s.held_since is None:
                continue
            limit = self.params.order_wait if s.seq.last is not None else self.params.order_wait_first
            if now - s.held_since > limit:
                out += self._stop_waiting(index, s, f"waited {limit:.0f} s")
        return out

    def _hold(self, index: int, s: _Stream, seq: int, previous: int | None, item: Any, now: float) -> list[Delivery]:
        if seq in s.held:
            return [Delivery(index, seq, item, duplicate=True)]
        if not s.held:
            s.held_since = now
        s.held[seq] = (previous, item)
        if len(s.held) > self.params.max_held:
            return self._stop_waiting(index, s, f"more than {self.params.max_held} messages wait")
        return []

    def _stop_waiting(self, index: int, s: _Stream, reason: str) -> list[Delivery]:
        seq = min(s.held)
        log.warning("%s: %s on %s for seq %s, which seq %d follows; handling the %d held message(s) with a gap",
                    self.name, reason, s.name, s.held[seq][0], seq, len(s.held))
        return self._release(index, s, everything=True)

    def _end_recovery(self) -> list[Delivery]:
        self._recovering_until = None
        return [delivery for index, s in enumerate(self._streams) for delivery in self._release(index, s, everything=True)]

    def _release(self, index: int, s: _Stream, everything: bool = False) -> list[Delivery]:
        """The held messages that now follow on (all of them, in order, when `everything`)."""
        out = []
        while s.held:
            seq = min(s.held)
            previous, item = s.held[seq]
            if not everything and not s.follows_on(seq, previous):
                return out
            del s.held[seq]
            out.append(self._deliver(index, s, seq, item))
        s.held_since = None
        return out

    @staticmethod
    def _deliver(index: int, s: _Stream, seq: int, item: Any) -> Delivery:
        missing, stale = s.seq.check(seq, s.stride)
        return Delivery(index, seq, item, missing=missing, stale=stale)
