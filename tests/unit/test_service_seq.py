"""Gap and stale detection of the service base (services/common/sequencing.py: SeqTracker, Sequencer): a
stream's frames are Header.stride apart, so frames a replay skips on purpose are no gap."""

from schemas import Header, Time
from services.common.sequencing import Sequencer, SeqTracker


def test_frames_a_stride_skips_are_no_gap_and_a_lost_one_is():
    tracker = SeqTracker()
    assert [tracker.check(seq, 3) for seq in (6, 9, 12)] == [(0, False), (0, False), (0, False)]
    assert tracker.check(18, 3) == (1, False)   # 15 was lost
    assert tracker.check(12, 3) == (0, True)    # sent again
    plain = SeqTracker()
    assert [plain.check(seq) for seq in (0, 1, 4)] == [(0, False), (0, False), (2, False)]


def test_a_header_says_one_frame_apart_unless_told():
    assert Header(seq=3, stamp=Time(sec=0, nanosec=0)).stride == 1


def test_the_sequencer_counts_no_gap_for_a_stride_and_one_for_a_lost_frame():
    order = Sequencer()
    stream = order.stream("camera/frame", ordered=True)
    deliveries = [d for seq in (0, 3, 6, 12) for d in order.offer(stream, seq, None, seq, 0.0, stride=3)]
    assert [(d.seq, d.missing, d.stale) for d in deliveries] == [(0, 0, False), (3, 0, False), (6, 0, False), (12, 1, False)]
