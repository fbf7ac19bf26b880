"""`gridslam bench egomotion`: time per frame of every estimator at NuBot's and KITTI's image
sizes, as a Markdown table of medians; optionally against another checkout's estimators, or
with a profile of where the time goes.

Frames come from the rendered test room (services/benchmarks/box_room.py): a camera driving
forward 0.1 m and turning 1° per frame, stereo, so every estimator sees the same images.
Only `estimate()` is timed (not rendering or reading files); the first frame of each run
(no motion yet) is left out. OpenCV runs on ``--threads`` threads (default 1: one core).

``--reference DIR`` times (or profiles) the estimators of another gridslam checkout (e.g. made
by ``git worktree add /tmp/before <commit>``) on the same frames: a child process runs this
module's code with the other checkout's `services` package, its runs interleaved with ours so
that both see the same load, and the table adds its times and the speed-up. Times are
wall-clock and CPU (all threads of the process); on a shared machine the CPU time is the
steadier figure.
"""

from __future__ import annotations

import cProfile
import hashlib
import json
import math
import os
import pstats
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from services.common.errors import ConfigError
from services.egomotion import ESTIMATORS, make_estimator
try:
    from services.common.frames import Frame
except ImportError:   # a --reference checkout from before the frames moved out of services/source
    from services.source.frames import Frame
try:
    from services.benchmarks.box_room import BoxRoom, motion_pose, pinhole
except ImportError:   # a --reference checkout from before the room moved out of services/egomotion
    from services.egomotion.scene import BoxRoom, motion_pose, pinhole

PROFILE_ROWS = 16

# (label, width, height, horizontal field of view in degrees, stereo baseline in metres)
SIZES = (
    ("640×480 (NuBot)", 640, 480, 66.0, 0.12),
    ("1241×376 (KITTI)", 1241, 376, 82.0, 0.54),
)

# The reference's side: a child process whose `services` package is the other checkout's, running
# this module's own code (loaded from its file) against that checkout's estimators and scene.
_REFERENCE_CHILD = """
import importlib.util, sys
spec = importlib.util.spec_from_file_location("reference_bench", sys.argv[1])
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)
bench.serve(int(sys.argv[2]))
"""


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


def frames_digest(frames: list[Frame]) -> str:
    """A hash of the frames' images: the reference must time the very same frames."""
    return hashlib.sha1(b"".join(frame.left.tobytes() + frame.right.tobytes() for frame in frames)).hexdigest()


def _timed_pass(name: str, frames: list[Frame]) -> tuple[list[float], list[float]]:
    """Wall-clock and CPU seconds (all of the process's threads) of each estimate() of one pass."""
    estimator = make_estimator(name, frames[0].camera, _bench_params(name))
    estimator.estimate(frames[0])
    wall, cpu = [], []
    for frame in frames[1:]:
        start, start_cpu = time.perf_counter(), time.process_time()
        estimator.estimate(frame)
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return wall, cpu


def _bench_params(name: str) -> dict:
    # The mono estimator takes its scale from the frames' odometry here, so no ground-plane
    # fit is skipped or added by the scene; the other estimators run with their defaults.
    return {"scale_source": "auto"} if name == "mono" else {}


class Reference:
    """Another checkout's estimators, timed or profiled in a child process (`serve`)."""

    def __init__(self, folder: Path, threads: int) -> None:
        if not any((folder / "services" / room).is_file() for room in ("benchmarks/box_room.py", "egomotion/scene.py")):
            raise ConfigError(f"--reference {folder}: not a gridslam checkout (no services/benchmarks/box_room.py)")
        self._child = subprocess.Popen(
            [sys.executable, "-c", _REFERENCE_CHILD, __file__, str(threads)],
            cwd=folder, env={**os.environ, "PYTHONPATH": str(folder)}, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )

    def ask(self, mode: str, label: str, name: str, frames: list[Frame]) -> Any:
        """The child's answer to `serve`'s request (mode "time" or "profile")."""
        assert self._child.stdin is not None and self._child.stdout is not None
        self._child.stdin.write(json.dumps([mode, label, name, len(frames)]) + "\n")
        self._child.stdin.flush()
        line = self._child.stdout.readline()
        if not line:
            raise ConfigError(f"--reference: its {name} estimator failed at {label} (its error is above)")
        answer = json.loads(line)
        if answer["frames"] != frames_digest(frames):
            raise ConfigError("--reference: it renders other frames (its box room differs), so the times are not comparable")
        return answer["result"]

    def close(self) -> None:
        if self._child.stdin is not None:
            self._child.stdin.close()
        self._child.wait(timeout=30)


def serve(threads: int) -> None:
    """The reference child's loop: one JSON line [mode, size label, estimator, frames] in, one
    JSON line {"result": ..., "frames": digest of the frames} out."""
    cv2.setNumThreads(threads)
    cache: dict[tuple[str, int], list[Frame]] = {}
    for line in sys.stdin:
        mode, label, name, count = json.loads(line)
        if (label, count) not in cache:
            size = next(size for size in SIZES if size[0] == label)
            cache[label, count] = frames_for(*size[1:], count)
        frames = cache[label, count]
        result = _timed_pass(name, frames) if mode == "time" else profile(name, frames, PROFILE_ROWS)
        print(json.dumps({"result": result, "frames": frames_digest(frames)}), flush=True)


def profile(name: str, frames: list[Frame], top: int) -> list[tuple[str, float, float, float]]:
    """cProfile of one pass in CPU time: (function, calls per frame, own ms per frame,
    cumulative ms per frame) of the ``top`` functions by cumulative time under estimate()."""
    estimator = make_estimator(name, frames[0].camera, _bench_params(name))
    estimator.estimate(frames[0])
    profiler = cProfile.Profile(time.process_time)  # CPU time of all threads: what the load does not inflate
    profiler.enable()
    for frame in frames[1:]:
        estimator.estimate(frame)
    profiler.disable()
    count = len(frames) - 1
    rows = []
    for (filename, _, function), (_, calls, own, cumulative, _) in pstats.Stats(profiler).stats.items():  # type: ignore[attr-defined]
        if function == "<method 'disable' of '_lsprof.Profiler' objects>":
            continue
        where = function if filename == "~" else f"{Path(filename).stem}.{function}"
        rows.append((where, calls / count, 1000.0 * own / count, 1000.0 * cumulative / count))
    rows.sort(key=lambda row: -row[3])
    return rows[:top]


def _print_profiles(names: list[str], count: int, threads: int, reference: Reference | None) -> None:
    for label, width, height, fov, baseline in SIZES:
        frames = frames_for(width, height, fov, baseline, count)
        for name in names:
            sides = [("", profile(name, frames, PROFILE_ROWS))]
            if reference is not None:
                sides.append((" (reference)", reference.ask("profile", label, name, frames)))
            for side, rows in sides:
                print(f"\n{name}{side} at {label}: cProfile (CPU time) of {count - 1} frames, {threads} OpenCV thread(s)\n")
                print("| function | calls per frame | own CPU ms per frame | cumulative CPU ms per frame |")
                print("|:---------|----------------:|---------------------:|----------------------------:|")
                for where, calls, own, cumulative in rows:
                    print(f"| `{where}` | {calls:.1f} | {own:.2f} | {cumulative:.2f} |")


def main(argv: list[str] | None = None) -> int:
    # Imported here: a --reference checkout's child runs this file against its own `services`.
    from services.common.settings import CommandParser

    parser = CommandParser(prog="gridslam bench egomotion", description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=20, help="frames per run (default 20)")
    parser.add_argument("--repeats", type=int, default=2, help="runs per estimator and size (default 2)")
    parser.add_argument("--estimators", default=",".join(ESTIMATORS), help="comma-separated (default: all)")
    parser.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1: one core)")
    parser.add_argument("--reference", type=Path, help="another gridslam checkout to time (or profile) on the same frames")
    parser.add_argument("--profile", action="store_true", help="print where each estimator's time goes (cProfile, CPU time) instead")
    args = parser.parse_args(argv)
    names = [name.strip() for name in args.estimators.split(",") if name.strip()]
    unknown = [name for name in names if name not in ESTIMATORS]
    if unknown or args.frames < 2 or args.repeats < 1 or args.threads < 1:
        parser.error(f"unknown estimator(s) {', '.join(unknown)}" if unknown else "--frames must be >= 2, --repeats and --threads >= 1")
    cv2.setNumThreads(args.threads)

    reference = Reference(args.reference.resolve(), args.threads) if args.reference else None
    try:
        if args.profile:
            _print_profiles(names, args.frames, args.threads, reference)
            return 0
        load_before = os.getloadavg()[0]
        rows = []
        for label, width, height, fov, baseline in SIZES:
            frames = frames_for(width, height, fov, baseline, args.frames)
            for name in names:
                ours: tuple[list[float], list[float]] = ([], [])
                theirs: tuple[list[float], list[float]] = ([], [])
                for _ in range(args.repeats):  # interleaved: both see the same load
                    for times, (wall, cpu) in [(ours, _timed_pass(name, frames))] + (
                        [(theirs, reference.ask("time", label, name, frames))] if reference else []
                    ):
                        times[0].extend(wall)
                        times[1].extend(cpu)
                medians = [1000.0 * statistics.median(values) if values else math.nan for values in ours + theirs]
                rows.append((label, name, *medians))
    finally:
        if reference is not None:
            reference.close()
    load_after = os.getloadavg()[0]

    print(f"Ego-motion estimators, median time per frame ({args.frames - 1} frames × {args.repeats} runs each; "
          f"{args.threads} OpenCV thread(s); {os.cpu_count()} CPUs, load average {load_before:.2f} before, {load_after:.2f} after)\n")
    baseline_ms = {label: wall for label, name, wall, *_ in rows if name == "scanline"}
    if reference is None:
        print("| image | estimator | ms per frame (median) | CPU ms per frame | frames/s | × scanline time |")
        print("|:------|:----------|----------------------:|-----------------:|---------:|----------------:|")
        for label, name, wall, cpu, *_ in rows:
            ratio = f"{wall / baseline_ms[label]:.1f}" if label in baseline_ms else "n/a"
            print(f"| {label} | {name} | {wall:.2f} | {cpu:.2f} | {1000.0 / wall:.1f} | {ratio} |")
    else:
        print(f"Reference: {args.reference}\n")
        print("| image | estimator | ms per frame (median) | reference ms | speed-up | CPU ms per frame | reference CPU ms | CPU speed-up |")
        print("|:------|:----------|----------------------:|-------------:|---------:|-----------------:|-----------------:|-------------:|")
        for label, name, wall, cpu, reference_wall, reference_cpu in rows:
            print(f"| {label} | {name} | {wall:.2f} | {reference_wall:.2f} | {reference_wall / wall:.2f} | "
                  f"{cpu:.2f} | {reference_cpu:.2f} | {reference_cpu / cpu:.2f} |")
    return 0
