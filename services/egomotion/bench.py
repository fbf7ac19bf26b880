"""`gridslam bench egomotion`: time per frame of every estimator at NuBot's and KITTI's image
sizes, as a Markdown table of medians.

Frames come from the rendered test room (services/egomotion/scene.py): a camera driving
forward 0.1 m and turning 1° per frame, stereo, so every estimator sees the same images.
Only `estimate()` is timed (not rendering or reading files); the first frame of each run
(no motion yet) is left out.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time

import numpy as np

from services.egomotion import ESTIMATORS, make_estimator
from services.source.frames import Frame
from services.egomotion.scene import BoxRoom, motion_pose, pinhole

# (label, width, height, horizontal field of view in degrees, stereo baseline in metres)
SIZES = (
    ("640×480 (NuBot)", 640, 480, 66.0, 0.12),
    ("1241×376 (KITTI)", 1241, 376, 82.0, 0.54),
)


def frames_for(width: int, height: int, fov_deg: float, baseline: float, count: int) -> list[Frame]:
    camera = pinhole(width, height, fov_deg, baseline)
    room = BoxRoom(seed=0, half_width=4.0, half_depth=12.0)
    pose = np.eye(4)
    step = (0.1, 0.0, math.radians(1.0))
    frames = []
    for k in range(count):
        frames.append(room.frame(k, camera, pose, stereo=True, odometry=step if k else (0.0, 0.0, 0.0)))
        pose = pose @ motion_pose(*step)
    return frames


def time_estimator(name: str, frames: list[Frame], repeats: int) -> list[float]:
    """Seconds per estimate() over ``repeats`` passes through ``frames`` (first frames excluded)."""
    seconds: list[float] = []
    camera = frames[0].camera
    for _ in range(repeats):
        estimator = make_estimator(name, camera, _bench_params(name))
        estimator.estimate(frames[0])
        for frame in frames[1:]:
            start = time.perf_counter()
            estimator.estimate(frame)
            seconds.append(time.perf_counter() - start)
    return seconds


def _bench_params(name: str) -> dict:
    # The mono estimator takes its scale from the frames' odometry here, so no ground-plane
    # fit is skipped or added by the scene; the other estimators run with their defaults.
    return {"scale_source": "auto"} if name == "mono" else {}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="gridslam bench egomotion", description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=20, help="frames per run (default 20)")
    parser.add_argument("--repeats", type=int, default=2, help="runs per estimator and size (default 2)")
    parser.add_argument("--estimators", default=",".join(ESTIMATORS), help="comma-separated (default: all)")
    args = parser.parse_args(argv)
    names = [name.strip() for name in args.estimators.split(",") if name.strip()]
    unknown = [name for name in names if name not in ESTIMATORS]
    if unknown or args.frames < 2 or args.repeats < 1:
        parser.error(f"unknown estimator(s) {', '.join(unknown)}" if unknown else "--frames must be >= 2 and --repeats >= 1")

    load_before = os.getloadavg()[0]
    rows = []
    for label, width, height, fov, baseline in SIZES:
        frames = frames_for(width, height, fov, baseline, args.frames)
        for name in names:
            median = statistics.median(time_estimator(name, frames, args.repeats))
            rows.append((label, name, 1000.0 * median, 1.0 / median))
    load_after = os.getloadavg()[0]

    print(f"Ego-motion estimators, median time per frame ({args.frames - 1} frames × {args.repeats} runs each; "
          f"{os.cpu_count()} CPUs, load average {load_before:.2f} before, {load_after:.2f} after)\n")
    print("| image | estimator | ms per frame (median) | frames/s | × scanline time |")
    print("|:------|:----------|----------------------:|---------:|----------------:|")
    baseline_ms = {label: ms for label, name, ms, _ in rows if name == "scanline"}
    for label, name, ms, fps in rows:
        ratio = f"{ms / baseline_ms[label]:.1f}" if label in baseline_ms else "n/a"
        print(f"| {label} | {name} | {ms:.2f} | {fps:.1f} | {ratio} |")
    return 0
