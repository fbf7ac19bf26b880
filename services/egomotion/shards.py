"""Sharded ego-motion: several egomotion instances share one robot's frames, and the increments
are the same, bit for bit, whichever instance computes which frame. Pure core: frames and names
in, increments out (the service adapter decodes, publishes and watches membership).

One instance or several. An instance is told how many instances share the robot's frames
(`instances`: `gridslam run` passes its --egomotion-instances, a deployment sets it). One
instance runs the estimator frame after frame (FrameByFrame), exactly as `gridslam odometry`
does; only several run it in blocks, because only blocks make an increment independent of which
instance saw the frames before it. `block_size` is the one rule for both the runner (the frames
it keeps in flight) and the service.

Blocks. The stereo and mono estimators carry state from frame to frame (stereo: the keyframe,
the last motion that seeds tracking, the disparity that seeds stereo matching; mono: the last
motion and a median of recent ground scales), so an increment depends on every frame before it.
To make it depend on a bounded stretch only, the seqs are cut into blocks of `block` (block k:
seqs k·block … (k+1)·block − 1) and a fresh estimator runs through each block, primed with the
`warmup` frames held just before it (their own increments are dropped). If the block's first
increment fails (quality 0: a frame whose stereo matching failed, say) the block is run again
primed with one more frame, up to `warmup + retries` frames. Scanline and passthrough keep only
the previous frame, so for them this is exactly the estimator frame after frame; for stereo and
mono a block start drops that state (docs/pipeline.md has the measured effect; mono's blocks are
longer, `default_block`). Every instance runs the same blocks, so any number of them agree.

Shares. Every instance announces `since`: the first seq from which it can run a block exactly
(it has held every frame from `warmup + retries` frames before it). Block k goes to the
instances eligible for it (since ≤ the block's first seq) in turn, by sorted name:
eligible[k mod n]; when none is (a run's first frames, or a lone instance restarted mid-run
that missed the frames before), to the instances with the smallest `since`, which then prime
the block with what they hold.
"""

from __future__ import annotations

import bisect
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from services.common.settings import setting
from services.egomotion.base import Estimator, Increment

log = logging.getLogger(__name__)

BLOCK = 4     # frames per block by default (docs/pipeline.md: the measured trade-off)
WARMUP = 1    # frames a block is primed with
RETRIES = 1   # more frames tried when the block's first increment fails


def default_block(estimator_class: type) -> int:
    """Frames per block for an estimator: its own `shard_block` (mono's is longer), else BLOCK."""
    return int(getattr(estimator_class, "shard_block", BLOCK))


@dataclass(frozen=True)
class ShardParams:
    """How a robot's egomotion instances share its frames, declared once: keys of `[egomotion]`,
    GRIDSLAM_EGOMOTION_INSTANCES and _SHARD_BLOCK, flags --instances and --shard-block."""

    LABEL = "sharding"

    instances: int = setting(1, ge=1, help="egomotion instances sharing this robot's frames: 1 (this one alone) runs the "
                                           "estimator frame after frame, more run it in blocks the same way on every "
                                           "instance; give every instance the same number")
    shard_block: int = setting(0, ge=0, help=f"frames per block when several instances share the frames (0: the "
                                             f"estimator's own, {BLOCK}, mono 16); every instance must use the same")


def block_size(estimator_class: type, sharding: ShardParams) -> int | None:
    """Frames per block of the shared estimation, or None: frame after frame. One instance runs
    the estimator frame after frame; several run it in blocks of `shard_block` (0: the
    estimator's own, `default_block`), the same on every instance. The one rule for the
    egomotion service and for the frames `gridslam run` keeps in flight."""
    if sharding.instances <= 1:
        return None
    return sharding.shard_block or default_block(estimator_class)


def block_owner(seq: int, block: int, members: Mapping[str, float]) -> str | None:
    """The instance whose share holds frame `seq`, given every member's `since` (None: no member)."""
    if not members:
        return None
    index = seq // block
    eligible = sorted(name for name, since in members.items() if since <= index * block)
    if not eligible:
        least = min(members.values())
        eligible = sorted(name for name, since in members.items() if since == least)
    return eligible[index % len(eligible)]


class FrameHistory:
    """The newest `size` frames an instance received, in seq order, complete from the first one
    kept: frames arrive in order, so none between two held frames was missed."""

    def __init__(self, size: int, primed_by: int = WARMUP + RETRIES):
        self.size = size
        self.primed_by = primed_by
        self.frames: dict[int, Any] = {}
        self._seqs: list[int] = []
        self.evicted = False   # older frames were dropped to keep `size`
        self.since: int | None = None   # the first block start this instance can run exactly

    def add(self, seq: int, frame: Any) -> bool:
        """Keep `frame` (a frame older than the newest is one sent again: kept if not held yet
        and not older than the oldest held). Whether it is held."""
        if seq in self.frames:
            return True
        if self._seqs and seq < self._seqs[0]:
            return False
        bisect.insort(self._seqs, seq)
        self.frames[seq] = frame
        if self.since is None and len(self._seqs) > self.primed_by:
            self.since = self._seqs[self.primed_by]
        while len(self._seqs) > self.size:
            del self.frames[self._seqs.pop(0)]
            self.evicted = True
        return True

    def seqs_between(self, low: int, high: int) -> list[int]:
        """Held seqs in [low, high]."""
        return self._seqs[bisect.bisect_left(self._seqs, low):bisect.bisect_right(self._seqs, high)]

    def seqs_before(self, seq: int, count: int) -> list[int]:
        """The (at most) `count` held seqs just before `seq`."""
        end = bisect.bisect_left(self._seqs, seq)
        return self._seqs[max(0, end - count):end]


@dataclass
class Estimate:
    previous_seq: int | None   # the frame the increment starts from (None: the estimator's first)
    increment: Increment


class _Run:
    """One estimator running through one block."""

    def __init__(self, index: int, estimator: Estimator):
        self.index = index
        self.estimator = estimator
        self.last_fed: int | None = None   # the last frame given to the estimator
        self.last_good: int | None = None  # the last frame it estimated without raising

    def feed(self, seq: int, frame: Any) -> Estimate:
        self.last_fed = seq
        previous = self.last_good
        increment = self.estimator.estimate(frame)   # raises for a frame it cannot use: skipped
        self.last_good = seq
        return Estimate(previous, increment)


class FrameByFrame:
    """Increments of one estimator fed every frame in seq order: what one egomotion instance
    alone runs, and what `gridslam odometry` runs. `make(frame)` builds the estimator with the
    first frame (which brings the calibration); `frame_of(item)` turns what the service holds
    into the estimator's frame."""

    rebuilt = 0   # frames estimated again to rebuild a state: never, frame after frame

    def __init__(self, make: Callable[[Any], Estimator], frame_of: Callable[[Any], Any] = lambda item: item):
        self.make = make
        self.frame_of = frame_of
        self._run: _Run | None = None

    @property
    def last_fed(self) -> int | None:
        """The last frame given to the estimator (a frame not after it cannot be estimated now)."""
        return self._run.last_fed if self._run is not None else None

    def estimate(self, seq: int, item: Any) -> Estimate:
        """The increment of frame `seq`, which comes after every frame given before
        (ValueError otherwise); raises what the estimator raises for that frame."""
        if self.last_fed is not None and seq <= self.last_fed:
            raise ValueError(f"frame {seq} is not after frame {self.last_fed}, the last one estimated")
        frame = self.frame_of(item)
        if self._run is None:
            self._run = _Run(0, self.make(frame))
        return self._run.feed(seq, frame)


class BlockEstimation:
    """Increments of the frames in `history`, each computed by running a fresh estimator through
    its block (module docstring); consecutive frames of one block reuse the running estimator.

    `make(frame)` builds an estimator for a block whose first frame is `frame` (which brings the
    calibration); `frame_of(item)` turns what the history holds into the estimator's frame."""

    def __init__(self, make: Callable[[Any], Estimator], block: int, frame_of: Callable[[Any], Any] = lambda item: item,
                 warmup: int = WARMUP, retries: int = RETRIES):
        if block < 1:
            raise ValueError("block must be at least 1")
        self.make = make
        self.block = block
        self.frame_of = frame_of
        self.warmup = warmup
        self.retries = retries
        self.rebuilt = 0   # frames estimated again to rebuild a block's state (not the first of a block)
        self._warned = False
        self._run: _Run | None = None

    def estimate(self, seq: int, history: FrameHistory) -> Estimate:
        """The increment of held frame `seq`. Raises what the estimator raises for that frame."""
        index = seq // self.block
        before = history.seqs_before(seq, 1)
        run = self._run
        if run is not None and run.index == index and before and run.last_fed == before[0]:
            return run.feed(seq, self.frame_of(history.frames[seq]))
        return self._run_block(index, seq, history)

    def _run_block(self, index: int, seq: int, history: FrameHistory) -> Estimate:
        """Run block `index` from its primers up to `seq` with a fresh estimator."""
        start = index * self.block
        block = history.seqs_between(start, seq)   # the block's held frames up to seq (block[-1] == seq)
        frame = lambda held: self.frame_of(history.frames[held])  # noqa: E731
        for warmup in range(self.warmup, self.warmup + self.retries + 1):
            primers = history.seqs_before(start, warmup)
            if len(primers) < warmup and history.evicted and not self._warned:
                self._warned = True   # the history is too short for the frames in flight: no longer exact
                log.warning("block %d is primed with %d frame(s) instead of %d: the frames before it are no longer "
                            "held (more frames in flight than the history keeps?)", index, len(primers), warmup)
            run = self._run = _Run(index, self.make(frame(seq)))
            for primer in primers:
                self._feed_quietly(run, primer, frame)
            last_try = len(primers) < warmup or warmup == self.warmup + self.retries
            if block[0] == seq:
                estimate = run.feed(seq, frame(seq))
                if estimate.increment.quality > 0 or last_try:
                    return estimate
            elif self._feed_quietly(run, block[0], frame) > 0 or last_try:
                break
        for middle in block[1:-1]:
            self._feed_quietly(run, middle, frame)
        self.rebuilt += len(block) - 1
        return run.feed(seq, frame(seq))

    @staticmethod
    def _feed_quietly(run: _Run, seq: int, frame: Callable[[int], Any]) -> float:
        """Feed a frame whose increment is not wanted now; its quality (0 when the estimator
        refuses it: skipped, as it is wherever the block runs)."""
        try:
            return run.feed(seq, frame(seq)).increment.quality
        except Exception as error:   # noqa: BLE001 - the same frame raises the same way on every instance
            log.debug("frame %d skipped while running block %d again: %s", seq, run.index, error)
            return 0.0


class BlockEstimator:
    """An Estimator (frames in, one increment each) that runs estimators block by block, as the
    egomotion service does: offline, the increments a pipeline publishes with any number of
    instances (`gridslam odometry --shard-block N`). Frames come in seq order."""

    def __init__(self, make: Callable[[Any], Estimator], block: int, name: str, params: Any):
        self.name = name
        self.params = params
        self.block = block
        self.history = FrameHistory(max(2 * block, 16))
        self.blocks = BlockEstimation(make, block)

    def estimate(self, frame: Any) -> Increment:
        self.history.add(frame.seq, frame)
        return self.blocks.estimate(frame.seq, self.history).increment
