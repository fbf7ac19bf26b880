"""The source's frames in flight (services/source/replay.py) and its frames lap after lap
(services/source/laps.py), without Zenoh, on a fake clock: the window fills and opens with
cumulative acknowledgements; frames in flight go again after `resend_after` without an
acknowledgement, or `reconnect_settle` after camera/frame has subscribers again, led by the last
acknowledged ones; a live camera gives them up; the pace holds the rate; laps go on in seq and
stamps, and a resume starts in the right lap."""

import numpy as np
import pytest

from services.common.geometry import planar_motion
from services.common.frames import Frame
from services.source.laps import Laps
from services.source.replay import STALL_LOG_PERIOD_S, Pacer, ReplayController, ReplayParams
from services.source.window import AdaptiveWindow, WindowParams


def controller(**params) -> ReplayController:
    return ReplayController(ReplayParams(**{"window": 4, "resend_after": 5.0, "resend_acknowledged": 2, **params}))


def test_the_window_fills_and_cumulative_acknowledgements_open_it():
    replay = controller()
    for seq in range(4):
        assert not replay.full
        replay.sent(seq, f"frame {seq}", now=0.0)
    assert replay.full and replay.oldest == 0 and not replay.settled
    replay.acked(1, now=0.5)   # 0 and 1 are through
    assert not replay.full and list(replay.in_flight) == [2, 3] and list(replay.acknowledged) == ["frame 0", "frame 1"]
    replay.acked(9, now=0.6)   # beyond every frame in flight: all of them
    assert replay.settled and replay.frames_sent == 4


def test_without_flow_control_nothing_is_tracked():
    replay = controller(window=0)
    for seq in range(100):
        replay.sent(seq, None, now=0.0)
    assert not replay.full and replay.settled and replay.frames_sent == 100 and replay.resend_due(1e6) is None


def test_frames_in_flight_go_again_after_resend_after_led_by_the_last_acknowledged_ones():
    replay = controller()
    for seq in range(6):
        replay.sent(seq, seq, now=0.0)
    replay.acked(2, now=1.0)   # 0, 1, 2 acknowledged; 3, 4, 5 in flight
    assert replay.resend_due(now=6.0) is None   # 5 s after the last acknowledgement, not more
    resend = replay.resend_due(now=6.01)
    assert resend.frames == (1, 2, 3, 4, 5) and (resend.first, resend.in_flight, replay.resent) == (3, 3, 3)
    assert resend.reason == "no acknowledgement for 5.0 s"
    replay.resend_done(now=9.0)                 # sending them waited on the pipeline: the wait starts then
    assert replay.resend_due(now=14.0) is None and replay.resend_due(now=14.01) is not None


def test_frames_in_flight_go_again_once_camera_frame_has_its_subscribers_back():
    replay = controller()
    replay.subscribers(False, now=0.0)   # before the first frame: nothing is unreachable
    replay.subscribers(True, now=0.1)
    replay.sent(0, "a", now=1.0)
    replay.sent(1, "b", now=1.0)
    assert replay.resend_due(now=1.2) is None
    replay.subscribers(False, now=2.0)   # the router died
    replay.subscribers(True, now=3.0)    # and came back
    assert replay.resend_due(now=3.4) is None
    resend = replay.resend_due(now=3.5)
    assert resend.frames == ("a", "b") and resend.reason == "camera/frame has subscribers again"
    replay.resend_done(now=3.5)
    assert replay.resend_due(now=4.0) is None   # once


def test_a_live_camera_gives_its_frames_in_flight_up():
    replay = controller(live=True)
    replay.sent(0, "a", now=0.0)
    replay.sent(1, "b", now=0.0)
    resend = replay.resend_due(now=5.5)
    assert (resend.frames, resend.abandoned, replay.abandoned, replay.resent) == ((), 2, 2, 0)
    assert replay.settled and replay.resend_due(now=100.0) is None


def test_the_adaptive_window_sets_the_limit_and_learns_of_resends():
    replay = ReplayController(ReplayParams(window=8), AdaptiveWindow(WindowParams(maximum=8)))
    assert replay.limit == 1   # the first probe: one frame into an empty pipeline
    replay.sent(0, None, now=0.0)
    assert replay.full
    replay.acked(0, now=0.05)
    assert replay.limit == 3 and replay.flow.min_latency == pytest.approx(0.05)
    replay.sent(1, None, now=1.0)
    replay.resend_due(now=6.1)
    replay.acked(1, now=6.2)   # a frame sent again gives no latency sample
    assert replay.flow.min_latency == pytest.approx(0.05)


def test_a_full_window_says_so_every_stall_period():
    replay = controller()
    assert replay.stalled(now=0.0) is None and replay.stalled(now=STALL_LOG_PERIOD_S - 0.1) is None
    assert replay.stalled(now=STALL_LOG_PERIOD_S) == pytest.approx(STALL_LOG_PERIOD_S)
    assert replay.stalled(now=STALL_LOG_PERIOD_S + 1) is None
    replay.moving()
    assert replay.stalled(now=100.0) is None   # a new stall starts its own count


def test_the_pace_holds_the_rate_and_catches_up_at_most_a_second_after_a_stall():
    pacer = Pacer(rate=4.0)
    assert pacer.delay(0.0) == 0.0 and pacer.delay(0.0) == 0.25
    assert pacer.delay(0.25) == 0.0 and pacer.delay(0.3) == pytest.approx(0.2)
    # Stalled until 10 s: the frames of the last second go at once (4, and the one due now), then the pace.
    assert [pacer.delay(10.0) for _ in range(6)] == [0.0] * 5 + [0.25]
    assert Pacer(rate=0.0).delay(0.0) == 0.0


class Dataset:
    """Frames 10, 12, 14 (a step of 2), 0.2 s apart, the camera moving 1 m forward per frame."""

    seqs = (10, 12, 14)

    def __init__(self):
        self.frames = [Frame(seq, 0.1 * seq, np.zeros((2, 2), np.uint8), ground_truth=self.pose(i),
                             odometry=(1.0 if i else 0.0, 0.0, 0.0)) for i, seq in enumerate(self.seqs)]

    @staticmethod
    def pose(i: int) -> np.ndarray:
        pose = np.eye(4)
        pose[2, 3] = float(i)
        return pose

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, i):
        return self.frames[i]

    def __iter__(self):
        return iter(self.frames)

    def iterate(self, index: int):
        return iter(self.frames[index:])


def test_laps_go_on_in_seq_and_stamps_and_a_new_lap_moves_from_the_last_frame():
    laps = Laps(Dataset(), loop=True, step=2)
    frames = [laps.next() for _ in range(7)]
    assert [f.seq for f in frames] == [10, 12, 14, 16, 18, 20, 22]
    assert [f.stamp for f in frames] == pytest.approx([1.0, 1.2, 1.4, 1.6, 1.8, 2.0, 2.2])
    assert laps.laps == 2 and laps.read == 7
    assert frames[3].odometry == pytest.approx(planar_motion(Dataset.pose(2), Dataset.pose(0)))   # 2 m back
    assert frames[4].odometry == (1.0, 0.0, 0.0) and frames[0].odometry == (0.0, 0.0, 0.0)
    once = Laps(Dataset())
    assert [once.next().seq for _ in range(3)] == [10, 12, 14] and once.next() is None


@pytest.mark.parametrize("handled, expected", [(10, [10, 12]), (14, [14, 16]), (15, [16, 18]), (19, [20, 22]),
                                               (23, [24, 26])])
def test_a_resumed_source_starts_at_the_frame_in_its_lap(handled, expected):
    laps = Laps(Dataset(), loop=True, step=2)
    laps.resume_at(handled)
    frames = [laps.next(), laps.next()]
    assert [f.seq for f in frames] == expected
    assert [f.stamp for f in frames] == pytest.approx([0.1 * seq for seq in expected])


def test_a_resumed_source_without_loop_starts_at_the_frame_and_ends_at_the_last():
    laps = Laps(Dataset())
    assert laps.can_resume and laps.resume_at(12) == 1
    assert [laps.next().seq, laps.next().seq, laps.next()] == [12, 14, None]
