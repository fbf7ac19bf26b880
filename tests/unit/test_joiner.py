"""expmap's frame joiner (services/expmap/joiner.py), without Zenoh or a map: a frame goes out
when its pose, its view and every closure its view announces are in, in frame order whatever
the interleaving; a frame whose view never comes is skipped once a later view came; a frame the
map holds goes out at once, marked, and closures for it or already in hand are stale."""

import itertools

from services.expmap.joiner import FrameJoiner


def drain(joiner: FrameJoiner, mapped=None) -> list[tuple]:
    out = []
    while (frame := joiner.next(mapped)) is not None:
        out.append((frame.seq, frame.pose, frame.view, frame.closures, frame.in_map))
    return out


def test_a_frame_waits_for_its_pose_its_view_and_every_closure_the_view_announces():
    joiner = FrameJoiner()
    joiner.pose(0, "p0")
    assert drain(joiner) == []
    joiner.view(0, "v0", closures=2)
    assert drain(joiner) == []
    assert joiner.closure(0, 9, "c9", mapped=None)
    assert drain(joiner) == []
    assert not joiner.closure(0, 9, "c9 again", mapped=None)   # in hand already: stale
    assert joiner.closure(0, 4, "c4", mapped=None)
    assert drain(joiner) == [(0, "p0", "v0", ("c4", "c9"), False)]   # in the order of the frames they close


def in_frame_order(order, kind) -> bool:
    seqs = [seq for k, seq in order if k == kind]
    return seqs == sorted(seqs)


def test_the_frames_come_out_the_same_whatever_the_interleaving_of_the_topics():
    """Each topic in frame order (as its publisher sends it), the topics interleaved every way."""
    inputs = [("pose", 0), ("view", 0), ("pose", 1), ("closure", 1), ("view", 1), ("pose", 2), ("view", 2)]
    outcomes = set()
    orders = [order for order in itertools.permutations(inputs) if in_frame_order(order, "pose")
              and in_frame_order(order, "view")]
    assert len(orders) == 5040 // (3 * 2 * 3 * 2)
    for order in orders:
        joiner, out = FrameJoiner(), []
        for kind, seq in order:
            if kind == "pose":
                joiner.pose(seq, f"p{seq}")
            elif kind == "view":
                joiner.view(seq, f"v{seq}", closures=int(seq == 1))
            else:
                joiner.closure(seq, 0, f"c{seq}", mapped=None)
            out += drain(joiner)
        outcomes.add(tuple(out))
    assert outcomes == {((0, "p0", "v0", (), False), (1, "p1", "v1", ("c1",), False), (2, "p2", "v2", (), False))}


def test_a_frame_whose_view_never_comes_is_skipped_once_a_later_view_arrived():
    joiner = FrameJoiner()
    joiner.pose(0, "p0")
    joiner.pose(1, "p1")
    assert drain(joiner) == []
    joiner.view(1, "v1", closures=0)
    assert drain(joiner) == [(1, "p1", "v1", (), False)] and joiner.skipped == 1


def test_a_frame_the_map_holds_goes_out_at_once_and_its_closures_are_stale():
    joiner = FrameJoiner()
    assert not joiner.closure(5, 1, "c", mapped=5)
    joiner.pose(5, "p5")
    joiner.view(5, "v5", closures=1)   # its closure is not waited for: the map has the frame
    assert drain(joiner, mapped=5) == [(5, "p5", "v5", (), True)]
    joiner.pose(6, "p6")
    joiner.view(6, "v6", closures=0)
    assert drain(joiner, mapped=5) == [(6, "p6", "v6", (), False)]


def test_views_and_closures_of_frames_before_the_one_out_are_dropped():
    joiner = FrameJoiner()
    joiner.view(0, "v0", closures=1)    # its pose never comes (refused by the map's adapter)
    joiner.closure(0, 3, "c0", mapped=None)
    joiner.pose(1, "p1")
    joiner.view(1, "v1", closures=0)
    assert drain(joiner) == [(1, "p1", "v1", (), False)] and joiner.held == (0, 0, 0)
    joiner.pose(0, "p0 late")             # a frame that came too late waits for a view of its own
    assert drain(joiner) == []
