"""The place recognisers behind the loop-closure detector, one interface over three models:

    observe(seq, frame, keyframe_of, learn) -> Recognised   which place the frame is at, its possible closures
                                                     (without ``learn``, a localisation, it stores no place)
    store(match, keyframe) -> dict | None            a new place's keyframe is made: what to journal
    replay(seq, match, journal_view)                 rebuild what a journaled frame did
    start_session()                                  later frames are another session's
    len()                                            places stored

`frame` gives the frame's images (`left`, `right`, `camera`) and its ORB features
(`features`, found once, on first use); `keyframe_of(place)` the stored keyframe of a place (or
None). Everything a recogniser keeps is rebuilt from the journal's views, in frame order, so a
restarted service recognises exactly as the uninterrupted one.
"""

from __future__ import annotations

import base64
import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.loopclosure.bow import BagOfWords, BagVector, BowParams
from services.loopclosure.geometry import ClosureGeometry, Keyframe
from services.loopclosure.sequence import SequenceParams, Sequences
from services.loopclosure.templates import TemplateParams, ViewMatch, ViewTemplates
from services.loopclosure.vocabulary import Vocabulary, default_vocabulary

PLACE_RECOGNITIONS = ("scanline", "bow", "sequence")
# The default, chosen by `gridslam bench place-recognition` on real recordings and the synthetic
# worlds (docs/mapping.md, "Place recognition"); the presets tuned for RatSLAM's templates keep scanline.
DEFAULT_PLACE_RECOGNITION = "bow"


@dataclass(frozen=True)
class Recognised:
    match: ViewMatch                          # the place the frame is at (matched or new)
    votes: tuple[tuple[int, int], ...]        # possible closures: (place, the frame it was stored at), best first
    journal_view: dict | None = None          # what replay needs of this frame (besides a new place's: `store`)
    candidate: tuple[int, float] | None = None   # the best place's frame and score, higher is more alike


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode()


def _unb64(text: str, dtype, shape=None) -> np.ndarray:
    array = np.frombuffer(base64.b64decode(text), dtype=dtype)
    return array.reshape(shape) if shape is not None else array


class ScanlinePlaces:
    """RatSLAM's view templates (templates.py): a place is a template."""

    needs_keyframes = False

    def __init__(self, params: TemplateParams, recent_frames: int):
        self.templates = ViewTemplates(params)
        self.params = params

    def __len__(self) -> int:
        return len(self.templates)

    def observe(self, seq: int, frame, keyframe_of, learn: bool = True) -> Recognised:
        match = self.templates.observe(frame.left, seq, learn)
        votes = () if match.is_new else ((match.template_id, match.matched_frame),)
        candidate = (match.nearest_frame, -match.distance) if match.nearest_frame >= 0 else None
        return Recognised(match, votes, None, candidate)

    def store(self, match: ViewMatch, keyframe: Keyframe | None) -> dict:
        return {"patch": _b64(self.templates.patch(match.template_id))}

    def start_session(self) -> None:
        pass

    def replay(self, seq: int, match: ViewMatch, view: dict | None) -> None:
        if match.is_new:
            self.templates.add(_unb64(view["patch"], np.float32, (self.params.height, self.params.width)), seq)


class BowPlaces:
    """A bag of binary words (bow.py): a place is a keyframe's features, verified by the geometry."""

    needs_keyframes = True

    def __init__(self, params: BowParams, recent_frames: int):
        params.check()
        vocabulary = Vocabulary.load(Path(params.vocabulary)) if params.vocabulary else default_vocabulary()
        self.bow = BagOfWords(vocabulary, params, recent_frames)

    def __len__(self) -> int:
        return len(self.bow)

    def observe(self, seq: int, frame, keyframe_of, learn: bool = True) -> Recognised:
        features = frame.features
        recognition = self.bow.observe(seq, self.bow.bag(features.descriptors),
                                       lambda place: _verify(frame.geometry, keyframe_of(place), features))
        frames = self.bow.frames
        votes = tuple((place, frames[place]) for place in recognition.votes)
        candidate = (frames[recognition.best_old], float(recognition.best_old_inliers)) if recognition.best_old >= 0 else None
        if recognition.place >= 0:
            place = recognition.place
            match = ViewMatch(place, False, max(0.0, 1.0 - recognition.score), 0.0, frames[place], 0)
        elif learn or not frames:
            match = ViewMatch(len(frames), True, 0.0, 0.0, seq, 0)
        else:   # a localisation stores nothing: the frame is at the place it looks most like, if any
            place = max(recognition.best_old, 0)
            match = ViewMatch(place, False, 1.0, 0.0, frames[place], 0)
        return Recognised(match, votes, None, candidate)

    def store(self, match: ViewMatch, keyframe: Keyframe) -> dict:
        bag = self.bow.bag(keyframe.descriptors)
        self.bow.add(bag, match.matched_frame)
        return {"words": _b64(bag.words.astype(np.uint32)), "weights": _b64(bag.weights)}

    def start_session(self) -> None:
        pass

    def replay(self, seq: int, match: ViewMatch, view: dict | None) -> None:
        if match.is_new:
            self.bow.add(BagVector(_unb64(view["words"], np.uint32).astype(np.int64), _unb64(view["weights"], np.float32)),
                         seq)

    @property
    def vocabulary_id(self) -> str:
        """What identifies the vocabulary in a journal's header (its words and weights)."""
        vocabulary = self.bow.vocabulary
        digest = hashlib.sha1(np.concatenate(vocabulary.levels).tobytes() + vocabulary.idf.tobytes()).hexdigest()
        return f"{vocabulary.branching}^{vocabulary.depth}:{digest[:16]}"


def _verify(geometry: ClosureGeometry, keyframe: Keyframe | None, features) -> int:
    return 0 if keyframe is None else geometry.verify(keyframe, features)


class SequencePlaces:
    """SeqSLAM's sequences of patch-normalised images (sequence.py)."""

    needs_keyframes = False

    def __init__(self, params: SequenceParams, recent_frames: int):
        self.sequences = Sequences(params, recent_frames)

    def __len__(self) -> int:
        return len(self.sequences)

    def observe(self, seq: int, frame, keyframe_of, learn: bool = True) -> Recognised:
        image = self.sequences.image_of(frame.left)
        found = self.sequences.observe(seq, image, learn)
        frames = self.sequences.frames
        if found.place >= 0:
            match = ViewMatch(found.place, False, found.place_difference, 0.0, frames[found.place], 0)
        else:
            match = ViewMatch(len(frames), True, found.place_difference, 0.0, seq, 0)
        votes = ((found.vote, frames[found.vote]),) if found.vote >= 0 else ()
        candidate = (frames[found.best], -found.best_difference) if found.best >= 0 else None
        return Recognised(match, votes, {"image": _b64(image)}, candidate)

    def store(self, match: ViewMatch, keyframe: Keyframe | None) -> None:
        return None   # the frame's image (its journal view) is the place

    def start_session(self) -> None:
        self.sequences.start_session()

    def replay(self, seq: int, match: ViewMatch, view: dict | None) -> None:
        self.sequences.replay(seq, _unb64(view["image"], np.uint8, self.sequences.image_shape), match.is_new)


def recogniser(name: str, params, recent_frames: int):
    """The place recogniser ``name`` (PLACE_RECOGNITIONS) with its parameters."""
    return {"scanline": ScanlinePlaces, "bow": BowPlaces, "sequence": SequencePlaces}[name](params, recent_frames)

