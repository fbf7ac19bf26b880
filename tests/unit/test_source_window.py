"""The replay window that follows the pipeline (services/source/window.py), driven by a simulated
pipeline on a virtual clock: stages in series, each handling one frame at a time in order (a
frame's service time per stage given, optionally varied at random), the source sending a new
frame whenever fewer than the window are in flight, and each frame acknowledged when the last
stage is done with it."""

from __future__ import annotations

import random
import statistics
from dataclasses import dataclass

import pytest

from services.source.window import AdaptiveWindow, WindowParams


@dataclass
class Run:
    fps: float
    p50_ms: float
    p99_ms: float
    limits: list[int]   # the window after each acknowledgement
    acks: list[float]


def simulate(stages_s, frames: int = 1500, window: AdaptiveWindow | None = None, fixed: int = 8, jitter: float = 0.0,
             seed: int = 0, later=None) -> Run:
    """Replay `frames` frames through stages of the given service times (s); `jitter` varies each
    by up to ±that fraction; `later` = (frame, stages) changes the stages from that frame on."""
    rng = random.Random(seed)
    free_at = [0.0] * 8               # when each stage is done with its last frame
    in_flight: list[tuple[float, int, float]] = []   # (acknowledged at, seq, sent at), in order
    latencies, acks, limits = [], [], []
    seq = 0

    def send(now: float) -> None:
        nonlocal seq
        ready = now
        for k, service in enumerate(later[1] if later and seq >= later[0] else stages_s):
            ready = free_at[k] = max(free_at[k], ready) + service * (1 + jitter * rng.uniform(-1, 1))
        in_flight.append((ready, seq, now))
        if window is not None:
            window.sent(seq, now)
        seq += 1

    send(0.0)
    while in_flight:
        now, acked, sent_at = in_flight.pop(0)
        latencies.append(now - sent_at)
        acks.append(now)
        if window is not None:
            window.acked(acked, now)
            limits.append(window.limit)
        while seq < frames and len(in_flight) < (window.limit if window is not None else fixed):
            send(now)
    latencies.sort()
    return Run((len(acks) - 1) / (acks[-1] - acks[0]), 1e3 * statistics.median(latencies),
               1e3 * latencies[int(0.99 * len(latencies))], limits, acks)


MARGIN = WindowParams().margin


def rate_between(run: Run, first: int, last: int) -> float:
    return (last - first) / (run.acks[last] - run.acks[first])


def test_the_window_settles_where_the_slowest_stage_stays_busy():
    # 10, 30 and 10 ms: 33.3 frames/s, 50 ms through an empty pipeline, so 1.7 frames in flight,
    # rounded to 2, keep the 30 ms stage busy, and the margin adds its frames.
    stages = [0.010, 0.030, 0.010]
    fixed = simulate(stages)
    adaptive = AdaptiveWindow(WindowParams(maximum=8))
    run = simulate(stages, window=adaptive)
    assert adaptive.min_latency == pytest.approx(0.050)
    assert adaptive.rate == pytest.approx(1 / 0.030)
    assert statistics.mode(run.limits) == 2 + MARGIN
    assert run.fps >= 0.99 * fixed.fps   # the probes cost a little
    assert fixed.p50_ms == pytest.approx(8 * 30, rel=0.01)   # 8 frames in flight, one every 30 ms
    assert run.p50_ms == pytest.approx((2 + MARGIN) * 30, rel=0.01) and run.p99_ms <= (3 + MARGIN) * 30


@pytest.mark.parametrize("stages", [[0.010, 0.030, 0.010], [0.008, 0.036, 0.008, 0.008, 0.005], [0.012, 0.015, 0.012]],
                         ids=["one-slow-stage", "five-stages", "near-equal-stages"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_varying_stage_times_keep_the_throughput_at_a_fraction_of_the_latency(stages, seed):
    fixed = simulate(stages, jitter=0.5, seed=seed)
    run = simulate(stages, window=AdaptiveWindow(WindowParams(maximum=8)), jitter=0.5, seed=seed)
    assert run.fps >= 0.95 * fixed.fps
    assert run.p50_ms <= 0.8 * fixed.p50_ms
    assert run.p99_ms <= 0.9 * fixed.p99_ms


SHORT = [0.010, 0.030, 0.010]                        # 50 ms through an empty pipeline: 1.7 frames in flight
LONG = [0.010, 0.030, 0.010, 0.025, 0.025, 0.025]    # 125 ms at the same 33.3 frames/s: 4.2


@pytest.mark.parametrize("before, after, windows", [(SHORT, LONG, (2, 4)), (LONG, SHORT, (4, 2))], ids=["slower", "faster"])
def test_a_change_of_the_no_queue_latency_is_found_by_the_next_probe(before, after, windows):
    # From frame 600 on, three 25 ms stages more or fewer: the same slowest stage, another way
    # through. Frames waiting in queues show neither change; a probe frame shows both.
    window = AdaptiveWindow(WindowParams(maximum=8, probe_interval=5.0))
    run = simulate(before, window=window, later=(600, after))
    assert window.probes >= 9
    assert statistics.mode(run.limits[300:600]) == windows[0] + MARGIN
    assert statistics.mode(run.limits[-300:]) == windows[1] + MARGIN
    assert window.min_latency == pytest.approx(sum(after))
    assert rate_between(run, 1100, 1499) >= 0.97 / 0.030


def test_probes_send_a_frame_into_an_empty_pipeline_at_the_start_and_every_interval():
    window = AdaptiveWindow(WindowParams(maximum=8, probe_interval=4.0))
    assert window.limit == 1 and window.probing
    window.sent(0, 0.0)
    assert window.limit == 1 and not window.probing   # until the first probe frame is back
    window.acked(0, 0.05)
    assert window.min_latency == pytest.approx(0.05) and window.limit == 1 + MARGIN   # no rate yet: one frame and the margin
    window = AdaptiveWindow(WindowParams(maximum=8, probe_interval=4.0))
    run = simulate([0.010, 0.030, 0.010], frames=1500, window=window)   # 45 s
    assert run.limits[0] == 1 + MARGIN and statistics.mode(run.limits) == 2 + MARGIN   # from the first probe on
    assert window.probes == pytest.approx((run.acks[-1] - run.acks[0]) / 4.0, abs=1.5)
    # Each later probe holds the frames back until the pipeline is empty (the frames in flight come back one by one).
    settled = run.limits.index(2 + MARGIN)
    holds = [limits for limits in "".join(str(limit) for limit in run.limits[settled:]).split(str(2 + MARGIN)) if limits]
    assert holds == ["1" * (2 + MARGIN)] * (window.probes - 1)


def test_a_window_of_one_or_two_stays_within_its_maximum():
    stages = [0.010, 0.030, 0.010, 0.025, 0.025, 0.025]
    for maximum in (1, 2):
        run = simulate(stages, window=AdaptiveWindow(WindowParams(maximum=maximum)))
        assert max(run.limits) == maximum
        assert run.fps == pytest.approx(simulate(stages, fixed=maximum).fps, rel=0.03)


def test_frames_sent_again_give_no_latency_sample():
    window = AdaptiveWindow(WindowParams(maximum=8))
    window.sent(0, 0.0)
    window.resent()              # nothing acknowledged for a while: sent again at 10 s ...
    window.acked(0, 10.02)       # ... and answered from a replay buffer
    assert window.min_latency is None and window.probing and window.probes == 0
    window.sent(1, 10.02)        # the probe again
    window.acked(1, 10.12)
    assert window.min_latency == pytest.approx(0.10) and window.probes == 1


def test_an_acknowledgement_covers_every_earlier_frame():
    window = AdaptiveWindow(WindowParams(maximum=8, rate_span=3))
    window.sent(0, 0.0)
    window.acked(0, 0.1)          # the probe: 100 ms through an empty pipeline
    for seq in (1, 2, 3, 4):
        window.sent(seq, 0.1)
    window.acked(2, 0.2)          # 1 and 2
    window.acked(4, 0.3)          # 3 and 4
    window.acked(4, 0.4)          # again: nothing more
    assert window.rate == pytest.approx(2 / 0.1)   # the last 3 acknowledgements over 0.1 s
    assert window.limit == 2 + MARGIN


@pytest.mark.parametrize("bad", [{"maximum": 0}, {"margin": -1}, {"gain": 0.0}, {"probe_interval": 0.0}, {"rate_span": 1}])
def test_invalid_parameters_are_refused(bad):
    with pytest.raises(ValueError, match="invalid window parameters"):
        WindowParams(**bad)
