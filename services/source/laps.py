"""A source's frames as sent: once, or with `loop` lap after lap, and from where a resumed run is.

With `loop`, the frames start again at the first after the last, for ever (a demo that keeps
running): `seq` and the stamps go on from the last lap's, one frame step after its last frame,
so the pipeline sees one long run through the same world; the first frame of a new lap carries
its motion from the last one (the dataset's first frame has none of its own).

`resume_at(seq)` starts at the frame `seq` (the last frame every running service has handled,
services/source/service.py), in its lap when looping.

Pure: frames in, frames out (services/common/frames.py); no clock, no transport.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
from collections.abc import Iterator

from services.common.frames import Frame, FrameSource
from services.common.geometry import planar_motion

log = logging.getLogger(__name__)


class Laps:
    """The frames of `frames` as sent (`next`), lap after lap with `loop`."""

    def __init__(self, frames: FrameSource, loop: bool = False, step: int = 1):
        self.frames = frames
        self.loop = loop
        self.step = step                             # the source's frame step (seq goes on by it)
        self.laps = 0                                # laps completed
        self.first: Frame | None = None              # the first frame of the source, and the last one read
        self.last: Frame | None = None
        self.seq_offset, self.stamp_offset = 0, 0.0  # added to the frames of the current lap
        self.read = 0                                # frames handed out
        self._iterator: Iterator[Frame] = iter(frames)

    def next(self) -> Frame | None:
        """The next frame, as sent (None after the last, unless looping)."""
        frame = next(self._iterator, None)
        if frame is None and self.loop and self.first is not None:
            self._new_lap()
            frame = next(self._iterator, None)
        if frame is None:
            return None
        self.read += 1
        lap_start = self.laps > 0 and self.last is not None and self.last.seq > frame.seq
        previous, self.last = self.last, frame
        if self.first is None:
            self.first = frame
        if self.laps == 0:
            return frame
        if lap_start and previous.ground_truth is not None and frame.ground_truth is not None:
            # The dataset's first frame has no motion of its own; on a new lap it moved from the last one.
            frame = dataclasses.replace(frame, odometry=planar_motion(previous.ground_truth, frame.ground_truth))
        return dataclasses.replace(frame, seq=frame.seq + self.seq_offset, stamp=frame.stamp + self.stamp_offset)

    def lap_length(self, first: Frame, last: Frame) -> tuple[int, float]:
        """How far seq and the stamps go on per lap: to one frame step after the last frame's."""
        span = last.seq - first.seq
        return span + self.step, (last.stamp - first.stamp) * (span + self.step) / span if span else 0.0

    @property
    def can_resume(self) -> bool:
        """Whether this source can start mid-run (datasets, video files, the synthetic world)."""
        return hasattr(self.frames, "iterate")

    def resume_at(self, seq: int) -> int:
        """Go on at frame `seq` (in its lap when looping): the index of the frame that comes next
        in its lap (len(frames): past the lap's last frame, the next lap comes). Before the first
        frame only, and only where `can_resume`."""
        if self.loop:   # the lap of that frame, and the offsets of seq and stamps in it
            self.first, last = self.frames[0], self.frames[len(self.frames) - 1]
            lap_seqs, lap_stamps = self.lap_length(self.first, last)
            self.laps = max(seq - self.first.seq, 0) // lap_seqs
            self.seq_offset, self.stamp_offset = self.laps * lap_seqs, self.laps * lap_stamps
        index = bisect.bisect_left(self.frames.seqs, seq - self.seq_offset)
        if self.loop and index == len(self.frames):   # past the lap's last frame: the next lap comes
            self.last = last
        self._iterator = self.frames.iterate(index)
        return index

    def _new_lap(self) -> None:
        """Go on from the first frame."""
        seqs, stamps = self.lap_length(self.first, self.last)
        self.seq_offset += seqs
        self.stamp_offset += stamps
        self.laps += 1
        self._iterator = iter(self.frames)
        log.info("source: lap %d done (%d frames sent); starting lap %d at seq %d", self.laps, self.read, self.laps + 1,
                 self.first.seq + self.seq_offset)
