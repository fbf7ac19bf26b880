"""The source service: frames from datasets, a live camera or a synthetic world.

The core (this package minus the adapter) is pure: numpy and OpenCV only. Start with
``open_source("kitti:PATH", start=0, stop=None, step=1, preset=None, calibration=None)``
(spec.py); frames are ``services.common.frames.Frame``; docs/sources.md describes every source.
"""

from services.common.frames import Camera, Frame, FrameSource, SourceError
from services.source.spec import open_source

__all__ = ["Camera", "Frame", "FrameSource", "SourceError", "open_source"]
