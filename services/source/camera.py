"""A live camera that always hands out the newest frame.

A grabber thread reads the device as fast as it delivers and keeps one slot: the latest
frame. A consumer slower than the camera gets the newest frame each time and the frames in
between are dropped (and counted), never queued, so latency stays one frame however slow the
pipeline is (DESIGN.md, Runtime). ``seq`` counts every frame grabbed, so drops show as gaps.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Any, Callable, Iterator

import cv2
import numpy as np

from services.common.frames import Camera, Frame, SourceError

log = logging.getLogger(__name__)


class LiveCamera:
    """Frames from ``device`` (an index, a device path or a stream URL) through
    ``capture_factory`` (cv2.VideoCapture; tests pass a fake). Iterate it; it has no indexed
    access, and a length only when ``stop`` is given.

    ``start`` skips frames grabbed before seq ``start`` (camera warm-up), ``stop`` ends the
    iteration at seq ``stop``, ``step`` delivers frames at least ``step`` grabs apart.
    Opening waits up to ``timeout`` seconds for a first frame; a camera that stops delivering
    for ``timeout`` seconds ends the iteration with SourceError.
    """

    live = True
    # Failed reads in a row after which the device is considered gone.
    MAX_FAILED_READS = 50

    def __init__(
        self,
        device: int | str = 0,
        *,
        camera: Camera | None = None,
        grey: bool = False,
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        timeout: float = 5.0,
        capture_factory: Callable[[Any], Any] = cv2.VideoCapture,
    ):
        if start < 0 or (stop is not None and stop <= start) or step < 1:
            raise SourceError(f"camera {device}: invalid frame selection start={start} stop={stop} step={step}")
        self.name = f"camera:{device}"
        self._start, self._stop, self._step = start, stop, step
        self._grey = grey
        self._timeout = timeout
        self._capture = capture_factory(device)
        if not self._capture.isOpened():
            raise SourceError(f"camera {device}: cannot open the device")
        self._condition = threading.Condition()
        self._latest: tuple[int, float, np.ndarray] | None = None  # the one slot: (seq, stamp, image)
        self._grabbed = 0
        self._dropped = 0
        self._failure: str | None = None
        self._running = True
        self._thread = threading.Thread(target=self._grab_loop, name=f"grabber {device}", daemon=True)
        self._thread.start()
        with self._condition:
            if not self._condition.wait_for(lambda: self._latest is not None or self._failure, timeout):
                self.close()
                raise SourceError(f"camera {device}: no frame within {timeout:g} s")
            if self._latest is None:
                failure = self._failure
                self.close()
                raise SourceError(f"camera {device}: {failure}")
            height, width = self._latest[2].shape[:2]
        if camera is not None and camera.width and (camera.width, camera.height) != (width, height):
            self.close()
            raise SourceError(f"camera {device}: frames are {width}×{height} but the calibration is for {camera.width}×{camera.height}")
        self.camera = dataclasses.replace(camera, width=width, height=height) if camera is not None else None
        self.image_size = (width, height)

    @property
    def frames_grabbed(self) -> int:
        """Frames read from the device so far."""
        return self._grabbed

    @property
    def frames_dropped(self) -> int:
        """Frames replaced by a newer one before anyone took them."""
        return self._dropped

    def _grab_loop(self) -> None:
        failures = 0
        while self._running:
            ok, image = self._capture.read()
            stamp = time.time()
            if not ok or image is None:
                failures += 1
                if failures >= self.MAX_FAILED_READS:
                    with self._condition:
                        self._failure = f"{failures} failed reads in a row: the device stopped delivering"
                        self._condition.notify_all()
                    return
                time.sleep(0.01)
                continue
            failures = 0
            if self._grey and image.ndim == 3:
                image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            with self._condition:
                if self._latest is not None:
                    self._dropped += 1
                self._latest = (self._grabbed, stamp, image)
                self._grabbed += 1
                self._condition.notify_all()

    def latest(self, timeout: float | None = None) -> Frame:
        """The newest frame not yet handed out, waiting for one up to ``timeout`` seconds
        (the source's own timeout by default); SourceError when none comes."""
        timeout = self._timeout if timeout is None else timeout
        with self._condition:
            if not self._condition.wait_for(lambda: self._latest is not None or self._failure or not self._running, timeout):
                raise SourceError(f"{self.name}: no frame within {timeout:g} s")
            if self._latest is None:
                raise SourceError(f"{self.name}: {self._failure or 'closed'}")
            seq, stamp, image = self._latest
            self._latest = None
        return Frame(seq=seq, stamp=stamp, left=image, camera=self.camera)

    def __iter__(self) -> Iterator[Frame]:
        last = None
        while True:
            frame = self.latest()
            if self._stop is not None and frame.seq >= self._stop:
                return
            if frame.seq < self._start or (last is not None and frame.seq - last < self._step):
                continue
            last = frame.seq
            yield frame

    def __len__(self) -> int:
        if self._stop is None:
            raise TypeError(f"{self.name} is live: it has no length without a stop")
        return len(range(self._start, self._stop, self._step))

    def __getitem__(self, i: int) -> Frame:
        raise TypeError(f"{self.name} is live: iterate it, it has no indexed access")

    def close(self) -> None:
        """Stop the grabber thread and release the device."""
        self._running = False
        with self._condition:
            self._condition.notify_all()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._capture.release()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"LiveCamera({self.name!r}, grabbed {self._grabbed}, dropped {self._dropped})"
