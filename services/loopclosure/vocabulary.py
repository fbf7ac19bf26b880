"""A visual vocabulary of binary features: a k-majority tree (Nistér & Stewénius 2006; Gálvez-López
& Tardós 2012, DBoW2) over 256-bit ORB descriptors, and the idf weight of every word.

A descriptor is quantised by descending the tree: at each of `depth` levels it takes the child
whose centre is nearest in Hamming distance, so a word costs `branching × depth` distances and
the vocabulary has `branching ** depth` words. The tree is stored dense (level l holds
`branching ** (l + 1)` centres; a node with fewer distinct descriptors than children repeats its
last centre), so quantising is a handful of vectorised XOR-and-popcounts.

`train` builds one from the descriptors of a set of images: k-majority clustering (k-means with
k-means++ seeding where a centre is the bitwise majority of its members) level by level, and
each word's idf log(images / images containing it). The vocabulary shipped with gridslam
(`DEFAULT_FILE`) was trained with `gridslam vocabulary` on frames that gridslam renders itself
(docs/mapping.md, "Place recognition"); nothing in it comes from a dataset.

The file is a NumPy .npz with the keys `format`, `version`, `branching`, `depth`, `centres`
(uint8, one array of every level's centres), `idf` (float32 per word) and `trained_on` (text).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.common.errors import ConfigError, DataError

FORMAT = "gridslam-orb-vocabulary"
VERSION = 1
DESCRIPTOR_BYTES = 32          # ORB: 256 bits
DEFAULT_FILE = Path(__file__).resolve().parent / "data" / "orb_vocabulary.npz"


class VocabularyError(DataError):
    """A vocabulary file that cannot be read (the message names it and what is wrong)."""


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between binary descriptors broadcast against each other (uint8, last axis
    the descriptor's bytes), counted 64 bits at a time."""
    return np.bitwise_count(np.bitwise_xor(_words64(a), _words64(b))).sum(axis=-1, dtype=np.int32)


def _words64(descriptors: np.ndarray) -> np.ndarray:
    """The same bits as uint64 words (the last axis 8 times shorter)."""
    return np.ascontiguousarray(descriptors, dtype=np.uint8).view(np.uint64)


@dataclass(frozen=True, eq=False)
class Vocabulary:
    branching: int
    depth: int
    levels: tuple[np.ndarray, ...]   # level l: (branching ** (l + 1), 32) uint8 centres
    idf: np.ndarray                  # (words,) float32
    trained_on: str = ""

    @property
    def words(self) -> int:
        return self.branching ** self.depth

    @property
    def nbytes(self) -> int:
        return sum(level.nbytes for level in self.levels) + self.idf.nbytes

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """The word (int64 in 0..words−1) of every descriptor, (N, 32) uint8."""
        descriptors = np.ascontiguousarray(descriptors, dtype=np.uint8)
        if descriptors.ndim != 2 or descriptors.shape[1] != DESCRIPTOR_BYTES:
            raise ValueError(f"vocabulary: descriptors must be (N, {DESCRIPTOR_BYTES}) uint8, got {descriptors.shape}")
        node = np.zeros(len(descriptors), np.int64)
        children = np.arange(self.branching)
        for centres in self.levels:
            candidates = node[:, None] * self.branching + children[None, :]
            distances = hamming(descriptors[:, None, :], centres[candidates])
            node = candidates[np.arange(len(descriptors)), np.argmin(distances, axis=1)]
        return node

    def save(self, path: Path) -> None:
        np.savez_compressed(path, format=FORMAT, version=VERSION, branching=self.branching, depth=self.depth,
                            centres=np.concatenate(self.levels), idf=self.idf.astype(np.float32),
                            trained_on=self.trained_on)

    @classmethod
    def load(cls, path: Path) -> Vocabulary:
        """The vocabulary in ``path``; VocabularyError naming the file for anything else."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                contents = {key: data[key] for key in data.files}
        except FileNotFoundError:
            raise VocabularyError(f"{path}: vocabulary file not found") from None
        except (OSError, ValueError, zipfile.BadZipFile) as error:
            raise VocabularyError(f"{path}: not a vocabulary file ({error})") from None
        missing = sorted({"format", "version", "branching", "depth", "centres", "idf"} - set(contents))
        if missing or str(contents["format"]) != FORMAT:
            raise VocabularyError(f"{path}: not a {FORMAT} file" + (f" (no {', '.join(missing)})" if missing else ""))
        if int(contents["version"]) != VERSION:
            raise VocabularyError(f"{path}: vocabulary version {int(contents['version'])}, this build reads {VERSION}")
        branching, depth = int(contents["branching"]), int(contents["depth"])
        centres, idf = contents["centres"], contents["idf"]
        sizes = [branching ** (level + 1) for level in range(depth)]
        if branching < 2 or depth < 1 or centres.dtype != np.uint8 or centres.shape != (sum(sizes), DESCRIPTOR_BYTES) \
                or idf.shape != (branching ** depth,) or not np.all(np.isfinite(idf)):
            raise VocabularyError(f"{path}: damaged vocabulary (centres {centres.shape}, idf {idf.shape} for "
                                  f"branching {branching}, depth {depth})")
        levels = tuple(np.split(centres, np.cumsum(sizes)[:-1]))
        return cls(branching, depth, levels, idf.astype(np.float32), str(contents.get("trained_on", "")))


def _k_majority(descriptors: np.ndarray, k: int, rng: np.random.Generator, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """k centres of ``descriptors`` and each descriptor's centre (k-means++ seeding, bitwise-majority updates)."""
    n = len(descriptors)
    if n <= k:
        centres = descriptors if n else np.zeros((1, DESCRIPTOR_BYTES), np.uint8)
        return np.concatenate([centres, np.repeat(centres[-1:], k - len(centres), axis=0)]), np.arange(n)
    chosen = [int(rng.integers(n))]
    nearest = hamming(descriptors, descriptors[chosen[0]]).astype(np.float64)
    for _ in range(k - 1):
        weight = nearest ** 2
        pick = int(rng.choice(n, p=weight / weight.sum())) if weight.sum() > 0 else int(rng.integers(n))
        chosen.append(pick)
        nearest = np.minimum(nearest, hamming(descriptors, descriptors[pick]))
    centres = descriptors[chosen].copy()
    bits = np.unpackbits(descriptors, axis=1)
    assignment = np.zeros(n, np.int64)
    for _ in range(iterations):
        assignment = np.argmin(hamming(descriptors[:, None, :], centres[None, :, :]), axis=1)
        updated = centres.copy()
        for c in range(k):
            members = bits[assignment == c]
            if len(members):
                updated[c] = np.packbits(2 * members.sum(axis=0) > len(members))
        if np.array_equal(updated, centres):
            break
        centres = updated
    return centres, np.argmin(hamming(descriptors[:, None, :], centres[None, :, :]), axis=1)


def train(images: list[np.ndarray], branching: int = 10, depth: int = 4, iterations: int = 10, seed: int = 0,
          trained_on: str = "") -> Vocabulary:
    """A vocabulary from the descriptors of a set of images (one (N, 32) uint8 array each)."""
    if branching < 2 or depth < 1:
        raise ConfigError(f"vocabulary: branching must be ≥ 2 and depth ≥ 1, got {branching}, {depth}")
    sets = [np.asarray(d, np.uint8).reshape(-1, DESCRIPTOR_BYTES) for d in images]
    descriptors = np.concatenate(sets) if sets else np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
    if len(descriptors) < branching ** depth:
        raise ConfigError(f"vocabulary: {len(descriptors)} descriptors cannot train {branching ** depth} words")
    rng = np.random.default_rng(seed)
    groups = [np.arange(len(descriptors))]
    levels = []
    for _ in range(depth):
        centres = np.zeros((len(groups) * branching, DESCRIPTOR_BYTES), np.uint8)
        children = []
        for g, members in enumerate(groups):
            node_centres, assignment = _k_majority(descriptors[members], branching, rng, iterations)
            centres[g * branching:(g + 1) * branching] = node_centres
            children += [members[assignment == c] for c in range(branching)]
        levels.append(centres)
        groups = children
    vocabulary = Vocabulary(branching, depth, tuple(levels), np.zeros(branching ** depth, np.float32), trained_on)
    containing = np.zeros(vocabulary.words)
    for d in sets:
        if len(d):
            containing[np.unique(vocabulary.quantize(d))] += 1
    idf = np.log(len(sets) / np.maximum(containing, 1)).astype(np.float32)
    return Vocabulary(branching, depth, tuple(levels), idf, trained_on)


_DEFAULT: Vocabulary | None = None


def default_vocabulary() -> Vocabulary:
    """The vocabulary shipped with gridslam (loaded once per process)."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = Vocabulary.load(DEFAULT_FILE)
    return _DEFAULT
