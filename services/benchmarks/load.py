"""`gridslam bench load`: the whole stack with the source at its maximum rate on 1241×376 stereo
frames (the synthetic world rendered with KITTI's image size and calibration, driven for as many
laps as the frames need), and the memory of every process sampled from /proc while it runs:
peak resident memory (VmHWM), and resident memory early in the run against the end, which stays
flat when no queue grows (issue 7, "Load").

Ego-motion is the passthrough estimator and the integrator dead reckoning, so the run measures
the transport and the services' queues rather than the estimators; loop closure and the
experience map run as usual.
"""

from __future__ import annotations

import math
import os
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from services.benchmarks.pipeline import KITTI_CAMERA
from services.common.settings import CommandParser
from services.evaluation.results import format_table
from services.pipeline.runner import RunConfig, run_pipeline
from services.source.calibration import write_calibration

SAMPLE_PERIOD_S = 0.25
FRAMES_PER_LAP = 374   # the synthetic world's corridor loop at 0.1 m per frame


def memory_kib(pid: int) -> tuple[int, int] | None:
    """(VmRSS, VmHWM) of a process in KiB, or None once it is gone."""
    try:
        fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
        return int(fields["VmRSS"].split()[0]), int(fields["VmHWM"].split()[0])
    except (OSError, KeyError, ValueError):
        return None


def process_name(pid: int) -> str | None:
    """`router` or the service name of a `gridslam` child, from its command line."""
    try:
        words = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return None
    if "router" in words:
        return "router"
    if "service" in words and words.index("service") + 1 < len(words):
        return words[words.index("service") + 1]
    return None


def children(parent: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1]) == parent:
                    found.append(int(entry.name))
            except (OSError, IndexError, ValueError):
                continue
    return found


@dataclass
class ProcessMemory:
    name: str
    samples: list[tuple[int, int]] = field(default_factory=list)   # (frames done, VmRSS KiB)
    peak_kib: int = 0                                                # VmHWM, the kernel's high-water mark

    def rss_at(self, frames: int) -> int | None:
        """Resident memory at the first sample taken once `frames` frames were done."""
        return next((rss for done, rss in self.samples if done >= frames), None)


class MemorySampler(threading.Thread):
    """Samples the memory of this process (the runner and its recorder) and of its children."""

    def __init__(self, period: float = SAMPLE_PERIOD_S):
        super().__init__(name="memory sampler", daemon=True)
        self.period = period
        self.done_frames = 0
        self.processes: dict[int, ProcessMemory] = {}
        self._halt = threading.Event()

    def run(self) -> None:
        own = os.getpid()
        while not self._halt.is_set():
            for pid in [own, *children(own)]:
                name = "runner" if pid == own else process_name(pid)
                memory = memory_kib(pid) if name else None
                if memory is None:
                    continue
                record = self.processes.setdefault(pid, ProcessMemory(name))
                record.samples.append((self.done_frames, memory[0]))
                record.peak_kib = max(record.peak_kib, memory[1])
            self._halt.wait(self.period)

    def stop(self) -> None:
        self._halt.set()
        self.join()


@dataclass
class LoadResult:
    frames: int
    wall_time_s: float
    throughput_fps: float | None
    latency_ms: dict
    missing_frames: int
    processes: dict[int, ProcessMemory]
    restarts: dict


def measure_load(frames: int, folder: Path, listen: str, window: int = 8) -> LoadResult:
    """One `gridslam run` of `frames` 1241×376 stereo frames at the source's full rate, sampled."""
    calibration = folder / "kitti_1241x376.toml"
    write_calibration(calibration, KITTI_CAMERA)
    laps = max(2, math.ceil(frames / FRAMES_PER_LAP))   # the synthetic preset's world, driven long enough
    config = RunConfig(source="synthetic:0", preset="synthetic", world={"laps": laps}, calibration=calibration,
                       egomotion="passthrough", integrator="deadreckoning", n_frames=frames, listen=listen,
                       window=window)
    sampler = MemorySampler()

    def progress(done: int, total: int | None) -> None:
        sampler.done_frames = done

    sampler.start()
    started = time.monotonic()
    try:
        result = run_pipeline(config, folder / "run", progress=progress)
    finally:
        sampler.stop()
    online, final = result.metrics["stages"]["map_online"], result.metrics["stages"]["map"]
    restarts = {name: s["restarts"] for name, s in result.metrics["services"].items() if s.get("restarts")}
    return LoadResult(frames, time.monotonic() - started, online["throughput_fps"], online["latency_ms"],
                      final["missing_frames"], sampler.processes, restarts)


def growth(record: ProcessMemory, frames: int) -> tuple[int | None, int | None, float | None]:
    """RSS (KiB) once a quarter of the frames were done, RSS at the last sample before the last
    frame (not during shutdown), and the growth between them in MiB per 1000 frames."""
    early = record.rss_at(frames // 4)
    during = [(done, rss) for done, rss in record.samples if done < frames]
    if early is None or not during or during[-1][0] <= frames // 4:
        return early, during[-1][1] if during else None, None
    done, late = during[-1]
    return early, late, (late - early) / 1024 * 1000 / (done - frames // 4)


def memory_rows(result: LoadResult) -> list[tuple[str, str, str, str, str]]:
    """Per process: peak RSS, RSS at a quarter of the run and near its end, growth per 1000 frames."""
    rows = []
    for record in sorted(result.processes.values(), key=lambda record: record.name):
        early, late, rate = growth(record, result.frames)
        rows.append((record.name, f"{record.peak_kib / 1024:.0f}", "-" if early is None else f"{early / 1024:.0f}",
                     "-" if late is None else f"{late / 1024:.0f}", "-" if rate is None else f"{rate:+.1f}"))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench load", description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000, help="frames of the run (default 2000)")
    parser.add_argument("--listen", default="tcp/127.0.0.1:7462", help="router endpoint of the run")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        result = measure_load(args.frames, Path(tmp), args.listen)
    print(f"{result.frames} frames of 1241×376 stereo (synthetic world, passthrough ego-motion, dead reckoning, map), "
          f"source at full rate, window 8")
    print(format_table([
        ("throughput, frame to map pose", result.throughput_fps, "frames/s"),
        ("latency frame → map pose p50", result.latency_ms["p50"], "ms"),
        ("latency frame → map pose p99", result.latency_ms["p99"], "ms"),
        ("frames missing from the map", result.missing_frames, "frames"),
        ("wall time", result.wall_time_s, "s"),
    ]))
    print()
    print("| process | peak RSS (VmHWM) MiB | RSS at 1/4 of the run MiB | RSS near the end MiB | growth MiB per 1000 frames |")
    print("|:--|--:|--:|--:|--:|")
    for row in memory_rows(result):
        print("| " + " | ".join(row) + " |")
    if result.restarts:
        print(f"restarts: {result.restarts}")
    return 0
