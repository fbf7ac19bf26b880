"""Place recognition by sequences (SeqSLAM: Milford & Wyeth, ICRA 2012), a pure core.

Each frame becomes a small image (`width`×`height`, area-averaged grey) normalised patch by
patch to zero mean and unit deviation (`patch` pixels square: SeqSLAM's patch normalisation,
which takes out changes of lighting). Two frames differ by the mean absolute difference of
their normalised images.

A frame more than `new_place` from the last stored place is stored as a new place. To
recognise an earlier place, the last `length` frames are compared with the stored places along
straight lines in (frame, place) space: for an end place j and a speed v (places per frame,
`speeds` between `min_speed` and `max_speed`), frame t − k against place round(j − v·k); a
line's score is the mean of its differences. The ends tried are the `candidates` places nearest
the current frame (an HNSW index over the stored places' images, hnswlib), so the cost does not
grow with the map; only places stored at least `recent_frames` ago are in the index. The best
line is a vote for its end place when its score is within `match_threshold` and the best line
ending more than `length` places away is at least `uniqueness` times worse (SeqSLAM's test of
the best match against the next best outside its neighbourhood).
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import cv2
import hnswlib
import numpy as np

from services.common.settings import check, setting

HNSW_LINKS, HNSW_BUILD, HNSW_SEARCH, HNSW_SEED = 16, 40, 64, 100


@dataclass(frozen=True)
class SequenceParams:
    LABEL = "sequences"

    width: int = setting(32, ge=4, help="Columns of the small image.")
    height: int = setting(24, ge=4, help="Rows of the small image.")
    patch: int = setting(8, ge=2, help="Side of the squares normalised to zero mean and unit deviation, pixels of the small image.")
    length: int = setting(10, ge=2, help="Frames in a sequence (SeqSLAM's ds).")
    min_speed: float = setting(0.0, ge=0, help="Slowest line tried, places per frame.")
    max_speed: float = setting(1.5, gt=0, help="Fastest line tried, places per frame.")
    speeds: int = setting(16, ge=1, help="Line speeds tried between min_speed and max_speed.")
    new_place: float = setting(0.35, gt=0, help="Difference from the last stored place beyond which a frame is a new place.")
    match_threshold: float = setting(0.55, gt=0, help="Largest mean difference along the best line for a match.")
    uniqueness: float = setting(1.1, ge=1, help="How much worse the best line elsewhere must be, as a ratio.")
    candidates: int = setting(16, ge=1, help="Places nearest the current frame tried as line ends.")

    def check(self) -> None:
        check(self)


@dataclass(frozen=True)
class SequenceMatch:
    place: int               # the last stored place when the frame is still at it, else -1 (a new place)
    place_difference: float  # the frame's difference from the last stored place
    vote: int                # the place the best line ends at when it is a match, else -1
    best: int                # the best line's end place (-1: none tried)
    best_difference: float   # its score


class Sequences:
    def __init__(self, params: SequenceParams = SequenceParams(), recent_frames: int = 30):
        params.check()
        self.params = params
        self.recent_frames = recent_frames
        self.image_shape = (params.height, params.width)
        dim = params.width * params.height
        self._images = np.empty((64, dim), np.float32)
        self.frames: list[int] = []
        self._indexed = 0
        self._index = hnswlib.Index(space="l2", dim=dim)
        self._index.init_index(max_elements=len(self._images), ef_construction=HNSW_BUILD, M=HNSW_LINKS, random_seed=HNSW_SEED)
        self._index.set_num_threads(1)
        self._index.set_ef(HNSW_SEARCH)
        self._recent: collections.deque[np.ndarray] = collections.deque(maxlen=params.length)
        self._speeds = np.linspace(params.min_speed, params.max_speed, params.speeds)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def nbytes(self) -> int:
        """Memory of the stored places: their images and the index's copy and links of each."""
        dim = self._images.shape[1]
        return self._images.nbytes + self._indexed * (4 * dim + 8 * HNSW_LINKS + 16)

    def image_of(self, image: np.ndarray) -> np.ndarray:
        """The frame's small image (uint8 grey, area-averaged): what a journal keeps of a frame."""
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return cv2.resize(image, (self.params.width, self.params.height), interpolation=cv2.INTER_AREA)

    def normalised(self, small: np.ndarray) -> np.ndarray:
        """Patch normalisation: every `patch`×`patch` square to zero mean and unit deviation (flat)."""
        p = self.params.patch
        small = small.astype(np.float32) / 255.0
        out = np.zeros_like(small)
        for y in range(0, small.shape[0], p):
            for x in range(0, small.shape[1], p):
                block = small[y:y + p, x:x + p]
                std = float(block.std())
                out[y:y + p, x:x + p] = (block - block.mean()) / std if std > 1e-3 else 0.0
        return out.ravel()

    def observe(self, frame: int, small: np.ndarray, learn: bool = True) -> SequenceMatch:
        """One frame's small image (image_of): stored as a new place or not (never without
        ``learn``, a localisation: it is then at the last place), and its vote."""
        vector = self.normalised(small)
        self._index_old(frame)
        self._recent.appendleft(vector)
        vote, best, best_difference = self._search()
        difference = float(np.abs(self._images[len(self.frames) - 1] - vector).mean()) if self.frames else np.inf
        place = len(self.frames) - 1 if difference <= self.params.new_place or not learn else -1
        if place < 0:
            self._add(vector, frame)
        return SequenceMatch(place, difference if np.isfinite(difference) else 0.0, vote, best, best_difference)

    def replay(self, frame: int, small: np.ndarray, is_new: bool) -> None:
        """Rebuild what `observe` did for a journaled frame (its image, and whether it was stored)."""
        vector = self.normalised(small)
        self._index_old(frame)
        self._recent.appendleft(vector)
        if is_new:
            self._add(vector, frame)

    def start_session(self) -> None:
        """A later session: its sequences do not reach back into the last one's frames."""
        self._recent.clear()

    def _add(self, vector: np.ndarray, frame: int) -> None:
        count = len(self.frames)
        if count == len(self._images):
            self._images = np.concatenate([self._images, np.empty_like(self._images)])
            self._index.resize_index(len(self._images))
        self._images[count] = vector
        self.frames.append(frame)

    def _index_old(self, frame: int) -> None:
        """Index the places that have become old enough to be loop closures."""
        while self._indexed < len(self.frames) and self.frames[self._indexed] <= frame - self.recent_frames:
            self._index.add_items(self._images[self._indexed:self._indexed + 1], [self._indexed])
            self._indexed += 1

    def _search(self) -> tuple[int, int, float]:
        """(vote or -1, best line's end or -1, its score) over the indexed places."""
        p = self.params
        if self._indexed == 0 or len(self._recent) < p.length:
            return -1, -1, 0.0
        k = min(p.candidates, self._indexed)
        ends, _ = self._index.knn_query(self._recent[0][None, :], k=k)
        ends = np.sort(ends[0].astype(np.int64))
        steps = np.arange(p.length)
        # places[e, s, k]: the place frame t − k is compared with on the line ending at ends[e] at speed s.
        places = np.rint(ends[:, None, None] - self._speeds[None, :, None] * steps[None, None, :]).astype(np.int64)
        valid = (places >= 0).all(axis=2)
        unique, inverse = np.unique(np.clip(places, 0, None), return_inverse=True)
        queries = np.stack(self._recent)                                            # (length, dim), newest first
        table = np.abs(self._images[unique][None, :, :] - queries[:, None, :]).mean(axis=2)   # (length, places)
        differences = table[steps[None, None, :], inverse.reshape(places.shape)]
        scores = np.where(valid, differences.mean(axis=2), np.inf).min(axis=1)     # per end
        order = np.lexsort((ends, scores))
        best = int(order[0])
        if not np.isfinite(scores[best]):
            return -1, -1, 0.0
        elsewhere = scores[np.abs(ends - ends[best]) > p.length]
        unique = not len(elsewhere) or elsewhere.min() >= p.uniqueness * scores[best]
        vote = int(ends[best]) if scores[best] <= p.match_threshold and unique else -1
        return vote, int(ends[best]), float(scores[best])
