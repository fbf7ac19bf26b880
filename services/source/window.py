"""The replay window that follows the pipeline: how many frames a replaying source keeps in flight,
worked out from its own send and acknowledgement times (docs/pipeline.md, "Flow control").

With W frames in flight, a pipeline whose slowest stage handles R frames a second and whose
stages take L0 seconds end to end when nothing waits (the no-queue latency) delivers
min(W / L0, R) frames a second, and a frame's latency is W over that (Little's law). So W ≈
R × L0 (the bandwidth-delay product of TCP) keeps the slowest stage busy, and each frame more
only waits in a queue, adding 1/R to every frame's latency for no throughput. The controller
estimates both as TCP BBR does for a network path:

- R, the highest delivery rate of the last `rate_memory` s, each sample the rate of the last
  `rate_span` acknowledgements (before the first sample, the rate of those so far);
- L0, the latency of the last probe frame, lowered by any shorter one since. A probe holds new
  frames back until the pipeline is empty and sends one frame into it; the frames after it do
  not delay it (they queue behind it), so the source goes on at once. Probes come at the start
  and every `probe_interval` s; each costs the slowest stage about L0 of idle time. (Frames sent
  into a full window wait in queues, so without probes L0 could never grow with the pipeline.)

and keeps the window at gain × R × L0, rounded, + margin frames, within [1, maximum]: one frame until
the first probe frame is back, growing with the measured rate from there. The margin, frames
queued in front of the slowest stage, keeps it busy when the stages' times vary. A frame sent
again (the source's resend) yields no latency sample: services answer a frame they have handled
from their replay buffers, faster than they compute one.

Pure: every time is an argument (seconds on one monotonic clock); nothing here reads a clock.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass


@dataclass(frozen=True)
class WindowParams:
    maximum: int = 8               # the configured window: never more in flight
    margin: int = 2                # frames beyond gain × R × L0
    gain: float = 1.0
    probe_interval: float = 10.0   # s between probes of the no-queue latency
    rate_span: int = 16            # acknowledgements per delivery-rate sample
    rate_memory: float = 10.0      # s a rate sample counts in the highest-rate filter

    def __post_init__(self):
        if self.maximum < 1 or self.margin < 0 or self.gain <= 0 or self.probe_interval <= 0 or self.rate_span < 2 \
                or self.rate_memory <= 0:
            raise ValueError(f"invalid window parameters: {self}")


class AdaptiveWindow:
    """The window of frames in flight (`limit`), fed with every frame sent (`sent`), every
    acknowledgement (`acked`, cumulative: it acknowledges every frame up to its seq) and every
    resend (`resent`)."""

    def __init__(self, params: WindowParams = WindowParams()):
        self.params = params
        self.min_latency: float | None = None   # L0, s
        self.probes = 0                          # probes completed
        self._in_flight: collections.OrderedDict[int, float | None] = collections.OrderedDict()   # seq → sent at
        self._acks: collections.deque[float] = collections.deque(maxlen=params.rate_span)
        self._rates: collections.deque[tuple[float, float]] = collections.deque()   # (time, frames/s)
        self._probe_due = True                   # the next frame is to go into an empty pipeline
        self._probe_seq: int | None = None       # the frame that did, while in flight
        self._probed_at = 0.0

    @property
    def probing(self) -> bool:
        """Holding frames back until the pipeline is empty, for a probe frame."""
        return self._probe_due

    @property
    def rate(self) -> float | None:
        """R, frames/s: the highest rate sample of the last rate_memory s; before the first, the rate
        of the acknowledgements so far (the window grows from there)."""
        if self._rates:
            return max(rate for _, rate in self._rates)
        if len(self._acks) >= 2 and self._acks[-1] > self._acks[0]:
            return (len(self._acks) - 1) / (self._acks[-1] - self._acks[0])
        return None

    @property
    def limit(self) -> int:
        """Frames in flight before the source waits."""
        p = self.params
        if self._probe_due or self.min_latency is None:
            return 1
        rate = self.rate
        if rate is None:
            return min(p.maximum, 1 + p.margin)
        return max(1, min(p.maximum, math.floor(p.gain * rate * self.min_latency + 0.5) + p.margin))

    def sent(self, seq: int, now: float) -> None:
        """A new frame went out."""
        if self._probe_due and not self._in_flight:
            self._probe_due, self._probe_seq = False, seq
        self._in_flight[seq] = now

    def resent(self) -> None:
        """The frames in flight went out again: their acknowledgements give no latency sample."""
        self._in_flight = collections.OrderedDict.fromkeys(self._in_flight)
        if self._probe_seq is not None:
            self._probe_due, self._probe_seq = True, None

    def acked(self, seq: int, now: float) -> None:
        """Every frame up to seq has come through the pipeline."""
        while self._in_flight and next(iter(self._in_flight)) <= seq:
            done, sent_at = self._in_flight.popitem(last=False)
            if sent_at is None:
                continue
            latency = now - sent_at
            if done == self._probe_seq:   # it went into an empty pipeline: L0 as it is now
                self.min_latency, self._probe_seq, self._probed_at = latency, None, now
                self.probes += 1
            elif self.min_latency is not None:
                self.min_latency = min(self.min_latency, latency)
            self._acks.append(now)
            if len(self._acks) == self._acks.maxlen and now > self._acks[0]:
                self._rates.append((now, (len(self._acks) - 1) / (now - self._acks[0])))
        while self._rates and self._rates[0][0] < now - self.params.rate_memory:
            self._rates.popleft()
        if self.probes and self._probe_seq is None and not self._probe_due \
                and now - self._probed_at >= self.params.probe_interval:
            self._probe_due = True
