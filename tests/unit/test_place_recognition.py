"""Place recognition (services/loopclosure: vocabulary.py, bow.py, sequence.py, places.py), the
consistency rule's run confirmation, and the ground truth of revisits, on synthetic helpers and
on the real recordings in ../shared/data."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.errors import ConfigError
from services.evaluation.revisits import GroundTruthError, RevisitRanges, from_poses, read_ground_truth
from services.loopclosure.bow import BagOfWords, BagVector, BowParams, InvertedIndex, bag_of
from services.loopclosure.consistency import ConsistencyParams, ConsistencyRule
from services.loopclosure.detector import MemoryKeyframes
from services.loopclosure.sequence import SequenceParams, Sequences
from services.loopclosure.service import LoopClosureConfig
from services.loopclosure.vocabulary import Vocabulary, VocabularyError, default_vocabulary, train


def random_descriptors(rng, count: int) -> np.ndarray:
    return rng.integers(0, 256, (count, 32), dtype=np.uint8)


# --- the vocabulary ---------------------------------------------------------------------------
def test_a_trained_vocabulary_quantises_a_descriptor_and_its_noisy_copy_alike_and_survives_a_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    centres = random_descriptors(rng, 40)
    images = []
    for _ in range(30):   # each "image": copies of some of the centres with a few bits flipped
        chosen = centres[rng.integers(0, len(centres), 60)]
        flips = np.packbits(rng.random((60, 256)) < 0.03, axis=1)
        images.append(chosen ^ flips)
    vocabulary = train(images, branching=4, depth=3, trained_on="test")
    assert vocabulary.words == 64 and vocabulary.idf.shape == (64,)
    noisy = centres ^ np.packbits(rng.random((40, 256)) < 0.02, axis=1)
    assert np.mean(vocabulary.quantize(centres) == vocabulary.quantize(noisy)) > 0.9
    path = tmp_path / "v.npz"
    vocabulary.save(path)
    loaded = Vocabulary.load(path)
    assert np.array_equal(loaded.quantize(noisy), vocabulary.quantize(noisy)) and loaded.trained_on == "test"


def test_a_damaged_or_foreign_vocabulary_file_is_one_line_naming_it(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(VocabularyError, match="bad.npz: not a vocabulary file"):
        Vocabulary.load(bad)
    other = tmp_path / "other.npz"
    np.savez(other, something=np.zeros(3))
    with pytest.raises(VocabularyError, match="other.npz: not a gridslam-orb-vocabulary file"):
        Vocabulary.load(other)
    with pytest.raises(VocabularyError, match="missing.npz: vocabulary file not found"):
        Vocabulary.load(tmp_path / "missing.npz")


def test_the_shipped_vocabulary_is_small_and_covers_real_features(shared_data):
    import cv2

    from services.loopclosure.geometry import ClosureGeometry
    from services.loopclosure.vocabulary import DEFAULT_FILE

    vocabulary = default_vocabulary()
    assert vocabulary.words == 16 ** 4 and DEFAULT_FILE.stat().st_size < 3 * 2**20
    assert "synthetic" in vocabulary.trained_on   # trained on frames gridslam renders, no dataset
    features = ClosureGeometry().features(cv2.imread(str(shared_data / "nubot_scene1" / "left" / "000000.png")))
    words = vocabulary.quantize(features.descriptors)
    # Real features spread over many words (a vocabulary trained on rendered frames still covers them).
    assert len(np.unique(words)) > 0.6 * len(words)


# --- the bag of words -------------------------------------------------------------------------
def test_the_inverted_index_scores_equal_the_l1_score_computed_directly():
    rng = np.random.default_rng(1)
    words = 500
    index = InvertedIndex(words)
    bags = []
    for place in range(200):
        chosen = np.unique(rng.integers(0, words, 40))
        weights = rng.random(len(chosen)).astype(np.float32)
        bag = BagVector(chosen, (weights / weights.sum()).astype(np.float32))
        index.add(place, bag)
        bags.append(bag)
    query = bags[17]
    dense = np.zeros((len(bags), words))
    for i, bag in enumerate(bags):
        dense[i, bag.words] = bag.weights
    q = np.zeros(words)
    q[query.words] = query.weights
    expected = 1 - 0.5 * np.abs(dense - q).sum(axis=1)
    assert np.allclose(index.scores(query, len(bags)), expected, atol=1e-5)
    assert int(np.argmax(index.scores(query, len(bags)))) == 17


def test_a_posting_budget_reads_the_rarest_words_and_leaves_out_the_commonest():
    index = InvertedIndex(10)
    common, rare = 3, 7
    for place in range(100):   # every place holds the common word; place 42 alone the rare one
        words = [common, rare] if place == 42 else [common]
        index.add(place, BagVector(np.array(words), np.full(len(words), 1 / len(words), np.float32)))
    query = BagVector(np.array([common, rare]), np.array([0.5, 0.5], np.float32))
    full = index.scores(query, 100)
    assert np.allclose(full, index.scores(query, 100, max_postings=101))   # within the budget: every posting
    budgeted = index.scores(query, 100, max_postings=50)   # the common word's 100 postings do not fit
    assert budgeted[42] == pytest.approx(0.5) and np.count_nonzero(budgeted) == 1
    assert full[42] == pytest.approx(1.0) and np.count_nonzero(full) == 100


def test_a_frame_votes_for_the_old_place_it_verifies_and_is_at_the_recent_one():
    vocabulary = default_vocabulary()
    rng = np.random.default_rng(2)
    descriptors = [random_descriptors(rng, 150) for _ in range(60)]
    bow = BagOfWords(vocabulary, BowParams(), recent_frames=30)
    for frame, d in enumerate(descriptors):
        bow.add(bag_of(vocabulary, d), frame)
    # Frame 80 sees place 5 again (verified) and also place 59, stored at frame 59 (recent).
    inliers = {5: 80, 59: 120}
    recognition = bow.observe(80, bag_of(vocabulary, np.concatenate([descriptors[5][:100], descriptors[59][:50]])),
                              lambda place: inliers.get(place, 3))
    assert recognition.votes[0] == 5 and recognition.best_old == 5 and recognition.best_old_inliers == 80
    assert recognition.place == 59   # still at the recent place (120 inliers ≥ place_inliers)
    recognition = bow.observe(70, bag_of(vocabulary, descriptors[59]), lambda place: 200 if place == 59 else 2)
    assert recognition.place == 59 and recognition.votes == ()
    unknown = bow.observe(200, bag_of(vocabulary, random_descriptors(rng, 150)), lambda place: 5)
    assert unknown.place == -1 and unknown.votes == () and unknown.best_old_inliers == 5


def test_bow_parameters_are_checked_by_their_declaration():
    with pytest.raises(ConfigError, match="bag of words: invalid min_inliers = 3"):
        BowParams(min_inliers=3).check()
    config = LoopClosureConfig(bow_candidates=4)
    assert config.place_params().candidates == 4
    with pytest.raises(Exception, match="bow_candidates"):
        LoopClosureConfig(bow_candidates=0)


# --- sequences --------------------------------------------------------------------------------
def test_a_sequence_of_frames_revisiting_a_route_votes_for_its_places_and_new_views_do_not():
    rng = np.random.default_rng(3)
    route = [rng.integers(0, 256, (24, 32), dtype=np.uint8) for _ in range(60)]
    sequences = Sequences(SequenceParams(), recent_frames=30)
    for frame, image in enumerate(route):
        sequences.observe(frame, image)
    assert len(sequences) == 60   # every view unlike the last stored: a place each
    votes = []
    for k, image in enumerate(route[10:30]):   # the same stretch again, re-lit and noisy
        seen = np.clip(0.8 * image + 25 + rng.normal(0, 5, image.shape), 0, 255).astype(np.uint8)
        votes.append(sequences.observe(100 + k, seen).vote)
    assert votes[-1] == 29 and sum(v == 10 + k for k, v in enumerate(votes)) >= 8
    strangers = [sequences.observe(200 + k, rng.integers(0, 256, (24, 32), dtype=np.uint8)).vote for k in range(12)]
    assert all(v == -1 for v in strangers[-3:])


# --- the rule confirms the run ------------------------------------------------------------------
def test_a_confirmed_run_confirms_its_earlier_votes_once():
    rule = ConsistencyRule(ConsistencyParams())
    closures = [rule.update(100 + k, k, False, 10 + k) for k in range(12)]
    first = closures[6]
    assert [c is None for c in closures[:6]] == [True] * 6
    assert [(v.frame, v.matched_frame) for v in first.earlier] == [(100 + k, 10 + k) for k in range(6)]
    assert all(c.earlier == () for c in closures[7:])   # already confirmed: not again
    without = ConsistencyRule(ConsistencyParams(confirm_run=False))
    assert all(c is None or c.earlier == () for c in (without.update(100 + k, k, False, 10 + k) for k in range(12)))


def test_of_several_earlier_visits_a_frame_votes_for_the_one_that_continues_the_run():
    rule = ConsistencyRule(ConsistencyParams())
    for k in range(5):   # lap 2 replays lap 1 (offset 40)
        rule.update(140 + k, 40 + k, False, 100 + k)
    # Lap 3 at frame 145 looks like frame 105 (lap 2) and frame 65 (lap 1): the run continues with 105.
    assert rule.choose(145, [(3, 65), (45, 105)]) == (45, 105)
    assert rule.choose(145, [(9, 140)]) is None   # recent


# --- ground truth -------------------------------------------------------------------------------
def test_ground_truth_from_ranges_poses_and_a_mask(tmp_path):
    ranges = RevisitRanges.parse("180-204:0-40")
    assert ranges.is_true(190, 12) and not ranges.is_true(190, 60) and len(ranges.revisit_frames) == 25
    with pytest.raises(GroundTruthError, match="FIRST-LAST:FIRST-LAST"):
        RevisitRanges.parse("180:0")
    # A square loop driven twice: lap 2 revisits lap 1 in the same direction.
    t = np.arange(80)
    positions = np.column_stack((np.cos(2 * np.pi * t / 40) * 3, np.sin(2 * np.pi * t / 40) * 3))
    headings = 2 * np.pi * t / 40 + np.pi / 2
    truth = from_poses(positions, headings, radius=0.5, recent=30)
    assert truth.is_true(45, 5) and not truth.is_true(45, 25) and truth.revisit_frames == set(range(39, 80))   # frame 39 is 0.47 m before frame 0
    with pytest.raises(GroundTruthError, match="no such ground-truth file"):
        read_ground_truth(str(tmp_path / "nothing.png"))


def test_the_rtabmap_mask_has_its_44_revisit_frames(shared_data):
    truth = read_ground_truth(str(shared_data / "rtabmap_samples" / "loop_closures_gt.bmp"))
    assert truth.revisit_frames == set(range(40, 84)) and truth.is_true(60, 20) and not truth.is_true(60, 50)


# --- the detector on the real recording -------------------------------------------------------------
def test_bow_finds_the_rtabmap_revisits_and_joins_no_unmarked_frames(shared_data):
    from services.source.spec import open_source

    truth = read_ground_truth(str(shared_data / "rtabmap_samples" / "loop_closures_gt.bmp"))
    detector = LoopClosureConfig().detector(MemoryKeyframes())
    assert detector.place_recognition == "bow"   # the default
    confirmed = []
    for frame in open_source(f"images:{shared_data / 'rtabmap_samples' / 'images'}"):
        confirmed += [(c.frame, c.matched_frame) for c in detector.observe(frame.seq, frame.left, None, frame.camera).closures]
    found = {frame for frame, matched in confirmed if truth.is_true(frame, matched)}
    assert all(truth.is_true(frame, matched) for frame, matched in confirmed), confirmed
    assert len(found) >= 33, sorted(found)
