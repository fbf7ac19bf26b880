"""Timing shared by the benchmarks."""

from __future__ import annotations

import statistics
import time


def median_ms(call, repeats: int) -> tuple[float, float]:
    """Medians of wall-clock and of this thread's CPU time over ``repeats`` calls, ms. On a busy
    machine the CPU time stays close to what the wall clock shows on an idle one (the timed code
    runs in this thread)."""
    wall, cpu = [], []
    for _ in range(repeats):
        started, started_cpu = time.perf_counter(), time.thread_time()
        call()
        wall.append(time.perf_counter() - started)
        cpu.append(time.thread_time() - started_cpu)
    return 1000 * statistics.median(wall), 1000 * statistics.median(cpu)
