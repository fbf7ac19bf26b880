"""A camera-like source process for tests (CI has no camera): the real source service and
LiveCamera, whose capture device is replaced by one that delivers frames at a fixed rate, as a
camera does, whatever the consumer's pace. Run as `python -m tests.e2e.live_camera ...`."""

from __future__ import annotations

import argparse
import logging
import sys
import time

import numpy as np

from services.common.runtime import RuntimeConfig
from services.source.camera import LiveCamera
from services.source.service import SourceConfig, SourceService


class PacedCapture:
    """cv2.VideoCapture's interface over a moving pattern delivered every 1/fps seconds."""

    def __init__(self, fps: float, width: int, height: int):
        self.period, self.width, self.height = 1.0 / fps, width, height
        self.due = time.monotonic()
        self.count = 0
        self.rng = np.random.default_rng(0)
        self.texture = self.rng.integers(0, 256, (height, width * 2), dtype=np.uint8)

    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return True

    def read(self):
        self.due += self.period
        delay = self.due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        self.count += 1
        shift = (3 * self.count) % self.width   # the view pans: consecutive frames differ by 3 columns
        return True, np.ascontiguousarray(self.texture[:, shift:shift + self.width])

    def release(self) -> None:
        pass


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-e", "--connect", required=True)
    parser.add_argument("--robot", default="robot0")
    parser.add_argument("--fps", type=float, default=200.0)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--live-window", type=int, default=2)
    parser.add_argument("--ack-topic", default="grid/pose")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    width, height = (int(v) for v in args.size.split("x"))
    camera = LiveCamera("paced", capture_factory=lambda device: PacedCapture(args.fps, width, height))
    config = SourceConfig(source="camera:paced", live_window=args.live_window, ack_topic=args.ack_topic, exit_at_end=False)
    runtime = RuntimeConfig(connect=[args.connect], robot=args.robot)
    try:
        return SourceService(runtime, config, camera, instance="live").run()
    finally:
        camera.close()


if __name__ == "__main__":
    sys.exit(main())
