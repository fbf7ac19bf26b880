"""What every source yields and every stage reads: frames with a sequence number, a time, images
and, when the data has them, ground truth and odometry. Pure data types: no I/O here (the
source's datasets.py, camera.py and synthetic.py produce them)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Protocol, runtime_checkable

import numpy as np

from services.common.errors import DataError


class SourceError(DataError):
    """A source's folder, file, image or calibration is missing or malformed (the message names it)."""


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics of the (rectified) left camera, in pixels; ``baseline`` is the
    distance between the left and right cameras in metres (0 for a monocular camera);
    ``width``/``height`` are the image size in pixels (0 when unknown)."""

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float = 0.0
    width: int = 0
    height: int = 0

    def matrix(self) -> np.ndarray:
        """The 3×3 intrinsic matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    ``seq`` is the frame's index in the dataset (a skipped frame leaves a gap), ``stamp`` its
    time in seconds. ``left`` (and ``right`` for stereo) are uint8 H×W grey or H×W×3 BGR images.
    ``ground_truth`` is the 4×4 pose of the camera in the first camera's frame, camera
    convention (x right, y down, z forward). ``odometry`` is the body-frame motion since the
    previous frame (forward m, left m, yaw rad counter-clockwise), e.g. wheel odometry.
    """

    seq: int
    stamp: float
    left: np.ndarray
    right: np.ndarray | None = None
    camera: Camera | None = None
    ground_truth: np.ndarray | None = None
    odometry: tuple[float, float, float] | None = None


@runtime_checkable
class FrameSource(Protocol):
    """A lazy, indexed sequence of frames: images are read on access. Iteration reports
    (one warning naming the file) and skips a frame that cannot be read, so the gap shows in
    ``seq``; indexed access raises SourceError for it instead."""

    camera: Camera | None

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Frame: ...

    def __iter__(self) -> Iterator[Frame]: ...
