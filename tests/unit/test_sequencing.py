"""The order a service handles its messages in (services/common/sequencing.py) and what it keeps
to recover (services/common/recovery.py), without Zenoh, on a fake clock: gaps and stale frames
named; messages held until the one they follow was delivered, for a bounded time; after a
reconnection, frames that skip ahead held until the ones between come, for a bounded time."""

from services.common.recovery import REPLAY_FRAMES, OutputMemory, RouterLink, new_run, sent_again
from services.common.sequencing import Sequencer, SequencerParams

PARAMS = SequencerParams(order_wait=20.0, order_wait_first=2.0, recovery=5.0, max_held=4)


def seqs(deliveries) -> list[tuple[int, int, bool]]:
    """(seq, missing, stale) of each delivery that is handled (duplicates left out)."""
    return [(d.seq, d.missing, d.stale) for d in deliveries if not d.duplicate]


def test_in_order_frames_go_through_and_gaps_and_stale_frames_are_named():
    order = Sequencer(PARAMS)
    s = order.stream("grid/pose", ordered=True)
    out = [d for seq in (0, 1, 4, 2, 5) for d in order.offer(s, seq, None, seq, now=0.0)]
    assert seqs(out) == [(0, 0, False), (1, 0, False), (4, 2, False), (2, 0, True), (5, 0, False)]
    assert [d.item for d in out] == [0, 1, 4, 2, 5] and order.last(s) == 5


def test_a_stream_resumed_from_a_checkpoint_takes_what_it_handled_as_stale():
    order = Sequencer(PARAMS)
    s = order.stream("egomotion", ordered=True, handled_up_to=7)
    assert seqs(order.offer(s, 7, None, None, 0.0) + order.offer(s, 8, None, None, 0.0)) == [(7, 0, True), (8, 0, False)]


def test_messages_published_out_of_order_are_delivered_in_the_order_their_links_give():
    order = Sequencer(PARAMS)
    s = order.stream("egomotion", ordered=True, follows=True)
    out = []
    # Two instances' blocks interleaved; 2 twice (once held, once after); 7 follows 5 (6 was never a frame).
    for seq, previous in ((0, None), (3, 2), (4, 3), (3, 2), (1, 0), (2, 1), (2, 1), (7, 5), (5, 4)):
        out += order.offer(s, seq, previous, seq, now=0.0)
    assert seqs(out) == [(0, 0, False), (1, 0, False), (2, 0, False), (3, 0, False), (4, 0, False), (2, 0, True),
                         (5, 0, False), (7, 1, False)]
    assert [d.seq for d in out if d.duplicate] == [3]   # it came twice while held: once is enough
    assert order.held(s) == [] and order.due(1000.0) == []


def test_a_message_whose_predecessor_never_comes_waits_order_wait_then_goes_on_with_a_gap():
    order = Sequencer(PARAMS)
    s = order.stream("egomotion", ordered=True, follows=True)
    assert seqs(order.offer(s, 0, None, None, now=10.0)) == [(0, 0, False)]
    assert order.offer(s, 2, 1, None, now=10.0) == [] and order.offer(s, 3, 2, None, now=11.0) == []
    assert order.due(now=30.0) == []                               # 20 s from the first held, not yet
    assert seqs(order.due(now=30.5)) == [(2, 1, False), (3, 0, False)]
    assert order.due(now=100.0) == []


def test_before_the_first_delivery_a_link_is_waited_for_only_order_wait_first():
    order = Sequencer(PARAMS)
    s = order.stream("egomotion", ordered=True, follows=True)
    assert order.offer(s, 5, 4, None, now=0.0) == []               # a service started mid-run: 4 went before it
    assert order.due(now=1.9) == [] and seqs(order.due(now=2.1)) == [(5, 0, False)]


def test_too_many_held_messages_end_the_wait_at_once():
    order = Sequencer(PARAMS)
    s = order.stream("egomotion", ordered=True, follows=True)
    order.offer(s, 0, None, None, 0.0)
    held = [d for seq in range(2, 6) for d in order.offer(s, seq, seq - 1, None, 0.0)]
    assert held == [] and order.held(s) == [2, 3, 4, 5]
    assert seqs(order.offer(s, 6, 5, None, 0.0)) == [(2, 1, False), (3, 0, False), (4, 0, False), (5, 0, False),
                                                     (6, 0, False)]


def test_after_a_reconnection_frames_that_skip_ahead_wait_for_the_ones_between():
    order = Sequencer(PARAMS)
    pose = order.stream("grid/pose", ordered=True)
    closure = order.stream("loop/closure", ordered=False)   # sparse: it skips frames by design
    for seq in (0, 1):
        order.offer(pose, seq, None, None, 0.0)
    order.offer(closure, 0, None, None, 0.0)
    order.reconnected(now=100.0)
    assert order.recovering
    # 4 and 5 were queued in a sender and outlived the router; 2 and 3 were lost in it, and come again.
    assert order.offer(pose, 4, None, None, 100.1) == [] and order.offer(pose, 5, None, None, 100.2) == []
    assert [d.duplicate for d in order.offer(pose, 5, None, None, 100.2)] == [True]
    assert seqs(order.offer(closure, 9, None, None, 100.2)) == [(9, 8, False)]   # not held
    assert seqs(order.offer(pose, 2, None, None, 100.3)) == [(2, 0, False)]
    assert seqs(order.offer(pose, 3, None, None, 100.4)) == [(3, 0, False), (4, 0, False), (5, 0, False)]
    # A real gap (a skipped file) waits until the recovery is over, then goes on with the gap counted.
    assert order.offer(pose, 8, None, None, 101.0) == []
    assert order.due(now=105.0) == [] and order.recovering
    assert seqs(order.due(now=105.1)) == [(8, 2, False)] and not order.recovering
    assert seqs(order.offer(pose, 10, None, None, 105.2)) == [(10, 1, False)]   # no longer held


def test_too_many_frames_held_after_a_reconnection_end_the_recovery_of_every_stream():
    order = Sequencer(PARAMS)
    pose, view = order.stream("grid/pose", ordered=True), order.stream("view/template", ordered=True)
    for stream in (pose, view):
        order.offer(stream, 0, None, None, 0.0)
    order.reconnected(now=0.0)
    assert order.offer(view, 3, None, None, 0.1) == []
    for seq in range(2, 6):
        assert order.offer(pose, seq, None, None, 0.1) == []
    out = order.offer(pose, 6, None, None, 0.1)
    assert [(d.stream, d.seq, d.missing) for d in out] == [(pose, 2, 1), (pose, 3, 0), (pose, 4, 0), (pose, 5, 0),
                                                           (pose, 6, 0), (view, 3, 2)]
    assert not order.recovering


def test_output_memory_keeps_the_last_frames_outputs_in_frame_order():
    memory = OutputMemory(frames=2)
    for seq, topic in ((1, "grid/pose"), (1, "grid/activity"), (2, "grid/pose"), (3, "grid/pose")):
        memory.remember(seq, topic, f"{topic}@{seq}")
    assert memory.of(1) == [] and memory.of(2) == [("grid/pose", "grid/pose@2")] and len(memory) == 2
    assert memory.of(3) == [("grid/pose", "grid/pose@3")]


def test_an_output_is_sent_again_when_it_is_of_a_kept_frame_not_newer_nor_far_back():
    assert not sent_again(None, 0) and not new_run(None, 0)        # the stream's first
    assert not sent_again(100, 101) and not new_run(100, 101)      # the next frame
    assert sent_again(100, 100) and sent_again(100, 100 - REPLAY_FRAMES) and not new_run(100, 100 - REPLAY_FRAMES)
    assert not sent_again(100, 99 - REPLAY_FRAMES) and new_run(100, 99 - REPLAY_FRAMES)   # far back: a new run


def test_the_router_link_is_down_when_the_last_router_left_and_back_once_when_one_returns():
    link = RouterLink()
    link.opened("a")
    link.opened("b")
    link.closed("a")
    assert not link.down and not link.back()     # b is still there
    link.closed("b")
    assert link.down and not link.back()
    link.opened("a")
    assert not link.down and link.back() and not link.back()
