"""Sharded ego-motion's core (services/egomotion/shards.py): one instance runs the estimator frame
after frame, several in blocks; which instance takes which frame, and blocks that give the same
increments whichever instance runs them, on real NuBot stereo pairs."""

import math

import pytest

from services.egomotion import EgomotionError, egomotion_config, estimator_params, make_estimator
from services.egomotion import ESTIMATORS
from services.egomotion.shards import (BLOCK, BlockEstimation, BlockEstimator, FrameByFrame, FrameHistory, ShardParams,
                                       block_owner, block_size)
from services.source.spec import open_source

# Frames 140–171 hold NuBot's hard spot: frame 152 repeats 151's left image with a new right one
# (its stereo matching fails) and 153 turns 23° (docs/egomotion.md).
FIRST, LAST = 140, 172


@pytest.fixture(scope="module")
def frames(shared_data):
    return list(open_source(f"stereo:{shared_data / 'nubot_scene1'}", start=FIRST, stop=LAST, step=1, preset="nubot"))


@pytest.fixture(scope="module")
def params():
    config = egomotion_config("nubot", environ={})
    return {name: estimator_params(config, name) for name in ESTIMATORS}


def blocks(name, params, block, **options):
    return BlockEstimation(lambda frame: make_estimator(name, frame.camera, params[name]), block, **options)


def history_of(frames, size=64):
    history = FrameHistory(size)
    for frame in frames:
        history.add(frame.seq, frame)
    return history


def as_tuple(estimate):
    increment = estimate.increment
    return estimate.previous_seq, increment.forward, increment.left, increment.yaw, increment.quality, increment.inliers


def test_shares_give_the_increments_of_one_instance(frames, params):
    one = blocks("stereo", params, 4)
    alone = history_of(frames)
    expected = {frame.seq: as_tuple(one.estimate(frame.seq, alone)) for frame in frames}
    assert sum(value[4] > 0 for value in expected.values()) >= len(frames) - 2   # a real run, not zeros

    # Three instances receive every frame, each estimates the frames of its share as they come.
    members = {"a": FIRST, "b": FIRST, "c": FIRST}
    instances = {name: (blocks("stereo", params, 4), FrameHistory(64)) for name in members}
    shared = {}
    for frame in frames:
        for name, (estimation, history) in instances.items():
            history.add(frame.seq, frame)
            if block_owner(frame.seq, 4, members) == name:
                shared[frame.seq] = as_tuple(estimation.estimate(frame.seq, history))
    assert shared == expected
    assert {block_owner(seq, 4, members) for seq in shared} == set(members)

    # An instance whose share changed estimates a frame in the middle of another's block: the
    # block is run again from its start, to the same increment.
    late = blocks("stereo", params, 4)
    assert as_tuple(late.estimate(FIRST + 14, alone)) == expected[FIRST + 14]
    assert late.rebuilt == 2


def test_scanline_in_blocks_is_the_plain_estimator(frames, params):
    """Scanline keeps only the previous frame: its blocks are exactly the unsharded run."""
    plain = make_estimator("scanline", frames[0].camera, params["scanline"])
    expected = [plain.estimate(frame) for frame in frames]
    estimation, history = blocks("scanline", params, 3), history_of(frames)
    got = [estimation.estimate(frame.seq, history) for frame in frames]
    assert [e.previous_seq for e in got] == [None] + [frame.seq for frame in frames[:-1]]
    assert [(g.increment.forward, g.increment.yaw) for g in got] == [(e.forward, e.yaw) for e in expected]
    # The same offline (`gridslam odometry --shard-block 3`).
    offline = BlockEstimator(lambda frame: make_estimator("scanline", frame.camera, params["scanline"]), 3, "scanline",
                             plain.params)
    assert [offline.estimate(frame).yaw for frame in frames] == [e.yaw for e in expected]


def test_a_block_whose_first_increment_fails_is_primed_with_one_more_frame(frames, params):
    history = history_of(frames)
    # Block 1 of 153 frames starts at frame 153; primed with 152 alone it has no keyframe.
    without = blocks("stereo", params, 153, retries=0).estimate(153, history)
    assert without.increment.quality == 0.0
    retried = blocks("stereo", params, 153).estimate(153, history)
    assert retried.previous_seq == 152 and retried.increment.quality > 0.5
    assert math.degrees(retried.increment.yaw) < -15   # the sudden turn


def test_a_refused_frame_is_skipped_the_same_way_by_every_instance(frames, params):
    mono = [frame if frame.seq != FIRST + 5 else type(frame)(**{**frame.__dict__, "right": None}) for frame in frames[:10]]
    history = history_of(mono)
    first = blocks("stereo", params, 4)
    results = {}
    for frame in mono:
        try:
            results[frame.seq] = as_tuple(first.estimate(frame.seq, history))
        except EgomotionError:
            results[frame.seq] = "refused"
    assert results[FIRST + 5] == "refused" and results[FIRST + 6][0] == FIRST + 4
    # Another instance runs the block from its start, through the refused frame.
    assert as_tuple(blocks("stereo", params, 4).estimate(FIRST + 7, history)) == results[FIRST + 7]


def test_block_owner_takes_turns_among_the_instances_that_hold_the_frames():
    members = {"b": 0, "a": 0}
    assert [block_owner(seq, 4, members) for seq in range(0, 16, 2)] == ["a", "a", "b", "b", "a", "a", "b", "b"]
    # c joined holding frames from 40 on: blocks before that stay with a and b.
    joined = {"a": 0, "b": 0, "c": 40}
    assert {block_owner(seq, 4, joined) for seq in range(0, 40)} == {"a", "b"}
    assert [block_owner(seq, 4, joined) for seq in range(40, 52, 4)] == ["b", "c", "a"]   # blocks 10, 11, 12: index mod 3
    # Nobody holds what block 0 needs: those with the oldest frames take it in turn.
    assert block_owner(1, 4, {"x": 12, "y": 12, "z": 30}) == "x"
    assert block_owner(5, 4, {"x": 12, "y": 12, "z": 30}) == "y"
    assert block_owner(5, 4, {"alone": math.inf}) == "alone"
    assert block_owner(5, 4, {}) is None


def test_history_is_complete_from_its_oldest_frame():
    history = FrameHistory(size=5, primed_by=2)
    for seq in (10, 11):
        history.add(seq, seq)
    assert history.since is None
    history.add(12, 12)
    assert history.since == 12   # two frames before any block that starts at 12 or later
    for seq in range(13, 20):
        history.add(seq, seq)
    assert list(history.frames) == [15, 16, 17, 18, 19] and history.evicted
    assert history.add(17, "again") and history.frames[17] == 17   # a frame sent again: already held
    assert not history.add(3, 3)   # older than what is held
    assert history.seqs_before(17, 2) == [15, 16] and history.seqs_between(16, 18) == [16, 17, 18]


def test_block_size_must_be_positive(params):
    with pytest.raises(ValueError, match="block"):
        blocks("stereo", params, 0)


def test_one_instance_runs_frame_after_frame_and_several_in_blocks():
    stereo, mono = ESTIMATORS["stereo"][0], ESTIMATORS["mono"][0]
    assert block_size(stereo, ShardParams()) is None and block_size(mono, ShardParams(shard_block=8)) is None
    assert block_size(stereo, ShardParams(instances=2)) == BLOCK == 4
    assert block_size(mono, ShardParams(instances=2)) == 16
    assert block_size(mono, ShardParams(instances=3, shard_block=8)) == 8


def test_frame_after_frame_is_the_estimator_fed_every_frame(frames, params):
    """What one egomotion instance publishes is what `gridslam odometry` computes (the same
    estimator, fed every frame); in blocks the stereo increments differ at block starts."""
    plain = make_estimator("stereo", frames[0].camera, params["stereo"])
    expected = [(frame.seq, plain.estimate(frame)) for frame in frames]
    alone = FrameByFrame(lambda frame: make_estimator("stereo", frame.camera, params["stereo"]))
    got = [alone.estimate(frame.seq, frame) for frame in frames]
    assert [e.previous_seq for e in got] == [None] + [frame.seq for frame in frames[:-1]]
    assert [as_tuple(e)[1:] for e in got] == [(i.forward, i.left, i.yaw, i.quality, i.inliers) for _, i in expected]
    assert alone.last_fed == frames[-1].seq
    with pytest.raises(ValueError, match="not after"):
        alone.estimate(frames[3].seq, frames[3])
    in_blocks, history = blocks("stereo", params, 4), history_of(frames)
    assert [as_tuple(in_blocks.estimate(frame.seq, history)) for frame in frames] != [as_tuple(e) for e in got]
