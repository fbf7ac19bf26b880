"""Place recognition by a bag of binary words (Sivic & Zisserman 2003; Gálvez-López & Tardós 2012,
DBoW2, ORB-SLAM's loop closer), a pure core.

A place is a frame that looked unlike every stored place. It keeps the ORB features of its
keyframe (services/loopclosure/geometry.py), quantised into the words of a vocabulary
(vocabulary.py): its bag of words is the vector of tf-idf weights (a word's count over the
place's features, times the word's idf), L1-normalised. Places are found through an inverted
index — per word, the places that hold it and their weights — and scored against the current
frame's bag by the L1 score of DBoW2, s(v, w) = 1 − ½‖v − w‖₁, which for two normalised
non-negative vectors is Σ min(vᵢ, wᵢ) over the words they share: only the postings of the
frame's own words are read, so scoring touches a small part of a large map; and at most
`max_postings` of them, the rarest words' first, so that its cost stops growing beyond a map of
about 25k places.

Per frame (`observe`): the `candidates` best-scoring places stored at least `recent_frames`
frames ago and the `recent_candidates` best of the recent ones are verified geometrically by the
caller (`verify(place) -> inliers`: the features' matches consistent with one camera motion,
ClosureGeometry.verify). The best verified old place is the frame's loop-closure *vote* (the
paper's rule counts them, consistency.py); the best verified place of either kind is the place
the frame is at; with none verified the frame is a new place. The raw score of a frame (for
precision–recall curves) is the inlier count of its best old candidate, verified or not.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Callable

import numpy as np

from services.common.settings import check, setting
from services.loopclosure.vocabulary import Vocabulary

_INITIAL_POSTINGS = 4


@dataclass(frozen=True)
class BowParams:
    LABEL = "bag of words"

    candidates: int = setting(6, ge=1, help="Best-scoring places stored at least recent_frames ago verified per frame.")
    recent_candidates: int = setting(2, ge=0, help="Best-scoring recent places verified per frame.")
    min_inliers: int = setting(30, ge=8, help="Matches fitting one camera motion for an earlier place to be recognised.")
    place_inliers: int = setting(60, ge=8, help="Matches with a recent place for the frame to be still at it "
                                               "(fewer: the frame is a new place).")
    vocabulary: str = setting("", help="Vocabulary file (gridslam vocabulary); empty: the one shipped with gridslam.")
    max_postings: int = setting(50_000, ge=1000, help="Postings of the inverted index read per frame at most, the "
                                "frame's rarest words first (a frame's scoring stops growing with the map; the words "
                                "skipped are the map's commonest). A map of 1000 places needs about 2000.")

    def check(self) -> None:
        check(self)


@dataclass(frozen=True)
class BagVector:
    """A sparse bag of words: distinct word ids (sorted) and their L1-normalised tf-idf weights."""

    words: np.ndarray     # int64
    weights: np.ndarray   # float32, sum 1 (or empty)


def bag_of(vocabulary: Vocabulary, descriptors: np.ndarray) -> BagVector:
    """The bag of words of a set of (N, 32) uint8 descriptors."""
    if len(descriptors) == 0:
        return BagVector(np.empty(0, np.int64), np.empty(0, np.float32))
    words, counts = np.unique(vocabulary.quantize(descriptors), return_counts=True)
    weights = counts * vocabulary.idf[words]
    total = float(weights.sum())
    return BagVector(words, (weights / total if total > 0 else weights).astype(np.float32))


class InvertedIndex:
    """Per word, the places holding it (int32) and their weights (float32), in growable arrays."""

    def __init__(self, words: int):
        self._places: list[np.ndarray | None] = [None] * words
        self._weights: list[np.ndarray | None] = [None] * words
        self._counts = np.zeros(words, np.int64)

    def add(self, place: int, bag: BagVector) -> None:
        for word, weight in zip(bag.words.tolist(), bag.weights.tolist()):
            n = int(self._counts[word])
            places = self._places[word]
            if places is None or n == len(places):
                grown = max(_INITIAL_POSTINGS, 2 * n)
                new_places, new_weights = np.empty(grown, np.int32), np.empty(grown, np.float32)
                if places is not None:
                    new_places[:n], new_weights[:n] = places, self._weights[word]
                self._places[word], self._weights[word] = new_places, new_weights
            self._places[word][n] = place
            self._weights[word][n] = weight
            self._counts[word] = n + 1

    def scores(self, bag: BagVector, places: int, max_postings: int | None = None) -> np.ndarray:
        """The L1 score of every place against ``bag`` (0 for a place sharing no word), from at
        most ``max_postings`` postings: the bag's words with the fewest places first, the
        commonest left out once the budget is spent (impact-ordered search, as text retrieval
        does it: those words add a little to most places' scores and tell them apart least)."""
        words, weights = bag.words, bag.weights
        counts = self._counts[words]
        if max_postings is not None and int(counts.sum()) > max_postings:
            rarest = np.argsort(counts, kind="stable")
            kept = np.sort(rarest[:int(np.searchsorted(np.cumsum(counts[rarest]), max_postings, side="right"))])
            words, weights = words[kept], weights[kept]
        ids, contributions = [], []
        for word, weight in zip(words.tolist(), weights.tolist()):
            n = int(self._counts[word])
            if n:
                ids.append(self._places[word][:n])
                contributions.append(np.minimum(self._weights[word][:n], weight))
        if not ids:
            return np.zeros(places, np.float32)
        return np.bincount(np.concatenate(ids), np.concatenate(contributions), minlength=places).astype(np.float32)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self._places if a is not None) * 2 + self._counts.nbytes


@dataclass(frozen=True)
class Recognition:
    """What `BagOfWords.observe` found: the recent place the frame is at (-1: none, the frame is a
    new place), its inliers and L1 score; the verified old places, most inliers first (the frame's
    possible loop closures); and the frame's raw score, the inliers of its best old candidate
    `best_old` (-1: no old place)."""

    place: int
    inliers: int
    score: float
    votes: tuple[int, ...]
    best_old: int
    best_old_inliers: int


class BagOfWords:
    """The stored places, their bags and the inverted index."""

    def __init__(self, vocabulary: Vocabulary, params: BowParams = BowParams(), recent_frames: int = 30):
        params.check()
        self.vocabulary = vocabulary
        self.params = params
        self.recent_frames = recent_frames
        self.index = InvertedIndex(vocabulary.words)
        self.frames: list[int] = []

    def __len__(self) -> int:
        return len(self.frames)

    def bag(self, descriptors: np.ndarray) -> BagVector:
        return bag_of(self.vocabulary, descriptors)

    def add(self, bag: BagVector, frame: int) -> int:
        """Store a place seen at ``frame``; returns its id."""
        place = len(self.frames)
        self.index.add(place, bag)
        self.frames.append(frame)
        return place

    def observe(self, frame: int, bag: BagVector, verify: Callable[[int], int]) -> Recognition:
        """Score the stored places against the frame's bag, verify the best (module docstring)."""
        count = len(self.frames)
        if count == 0:
            return Recognition(-1, 0, 0.0, (), -1, 0)
        scores = self.index.scores(bag, count, self.params.max_postings)
        old = bisect.bisect_right(self.frames, frame - self.recent_frames)   # places are stored in frame order
        chosen = _best(scores[:old], self.params.candidates)
        recent = _best(scores[old:], self.params.recent_candidates) + old
        inliers = {int(p): verify(int(p)) for p in np.concatenate([chosen, recent])}
        # The most inliers first; ties go to the higher score, then to the older place.
        rank = sorted(inliers, key=lambda p: (-inliers[p], -scores[p], p))
        votes = tuple(p for p in rank if p < old and inliers[p] >= self.params.min_inliers)
        place = next((p for p in rank if p >= old and inliers[p] >= self.params.place_inliers), -1)
        top_old = next((p for p in rank if p < old), -1)
        return Recognition(place, inliers.get(place, 0), float(scores[place]) if place >= 0 else 0.0, votes, top_old,
                           inliers.get(top_old, 0))

def _best(scores: np.ndarray, k: int) -> np.ndarray:
    """Indices of the k highest positive scores, best first (ties: lower index first)."""
    positive = np.flatnonzero(scores > 0)
    if len(positive) > k:
        positive = positive[np.argpartition(-scores[positive], k - 1, kind="introselect")[:k]]
    return positive[np.lexsort((positive, -scores[positive]))]
