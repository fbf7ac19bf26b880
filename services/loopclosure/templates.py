"""View templates (RatSLAM's local view cells; Milford & Wyeth 2008, Ball et al. 2013).

A frame's view template is a crop of the grey image, resized (area averaging) to a small
patch and normalised. It is compared with every stored template at horizontal shifts within
±`shift_range` columns by the mean absolute difference over the overlapping columns; the best
shift gives the rotation between the views. When no stored template is within
`match_threshold`, the view becomes a new template.

Matching costs the same at 1k or 100k templates: the candidates come from an approximate
nearest-neighbour index (hnswlib's HNSW graph, Malkov & Yashunin 2018) and only they are
compared patch to patch, exactly.
The index holds a compact descriptor of every stored template: its rows averaged into
`index_rows` bands, of its central columns (those that overlap the current view at every shift,
`shift_range` to `width − shift_range`). A frame asks the index once per shift s with its own
bands' columns moved by s, takes the `candidates` nearest of each, and verifies their union by
the mean absolute difference at every shift. A template close to the view patch-wise is close
descriptor-wise, so the index rarely misses the best match (`gridslam bench mapping` measures
it against the exhaustive search, `matcher = "exhaustive"`, which compares every template).
Templates are added to the index in the order they are stored, single-threaded, so the same
templates give the same index and the same answers (a restarted service replays them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import hnswlib
import numpy as np

from services.common.errors import ConfigError, DataError
from services.common.settings import setting


MATCHERS = ("index", "exhaustive")
# HNSW graph: links per node, and the breadth of construction and search (a wider search finds
# the nearest templates more surely for a few µs more); a fixed seed: the same templates give
# the same graph.
HNSW_LINKS = 16
HNSW_BUILD = 40
HNSW_SEARCH = 64
HNSW_SEED = 100


class TemplateError(DataError):
    """An image the view templates cannot use."""


@dataclass(frozen=True)
class TemplateParams:
    crop: tuple[float, float, float, float] = setting((0.0, 1.0, 0.0, 1.0), help="Crop x0, x1, y0, y1 as fractions of the image.")
    width: int = setting(60, ge=4, help="Template columns.")
    height: int = setting(10, ge=1, help="Template rows.")
    normalisation: float = setting(0.4, ge=0, help="Mean intensity each template is scaled to (0: none).")
    shift_range: int = setting(5, ge=0, help="Column shifts tried in each direction.")
    match_threshold: float = setting(0.085, gt=0, help="Distance below which a view matches a stored template.")
    fov_deg: float = setting(53.0, gt=0, le=360, help="Horizontal field of view of the image, degrees (for relative angles).")
    matcher: str = setting("index", choices=MATCHERS, help="index: candidates from a nearest-neighbour index, verified "
                                                            "exactly; exhaustive: every template.")
    candidates: int = setting(16, ge=1, help="Nearest templates per shift taken from the index, then compared exactly.")
    index_rows: int = setting(3, ge=1, help="Row bands of the index's template descriptor.")

    def check(self) -> None:
        x0, x1, y0, y1 = self.crop
        rules = [("crop", 0 <= x0 < x1 <= 1 and 0 <= y0 < y1 <= 1), ("width", self.width > 2 * self.shift_range),
                 ("height", self.height >= 1), ("shift_range", self.shift_range >= 0),
                 ("match_threshold", self.match_threshold > 0), ("fov_deg", 0 < self.fov_deg <= 360),
                 ("candidates", self.candidates >= 1), ("normalisation", self.normalisation >= 0),
                 ("matcher", self.matcher in MATCHERS), ("index_rows", 1 <= self.index_rows <= self.height)]
        for name, ok in rules:
            if not ok:
                raise ConfigError(f"view templates: invalid {name} = {getattr(self, name)!r}")


@dataclass(frozen=True)
class ViewMatch:
    """The result of observing one frame."""

    template_id: int          # matched or newly stored template
    is_new: bool
    distance: float           # to the best stored template (0 for a new template with no other)
    relative_angle: float     # radians, from the best shift (positive: the view turned left)
    matched_frame: int        # frame at which the template was stored
    shift: int                # best column shift
    nearest_frame: int = -1   # frame of the closest stored template, also when the view became a new one (-1: none)


class ViewTemplates:
    """Every stored template and the frame it was stored at."""

    def __init__(self, params: TemplateParams = TemplateParams()):
        params.check()
        self.params = params
        self._patches = np.empty((64, params.height, params.width), dtype=np.float32)
        self.frames: list[int] = []
        crop_fraction = params.crop[1] - params.crop[0]
        self.radians_per_column = math.radians(params.fov_deg) * crop_fraction / params.width
        self._index = None
        if params.matcher == "index":
            self._index = hnswlib.Index(space="l2", dim=params.index_rows * (params.width - 2 * params.shift_range))
            self._index.init_index(max_elements=len(self._patches), ef_construction=HNSW_BUILD, M=HNSW_LINKS,
                                   random_seed=HNSW_SEED)
            # One thread: the services share the cores, and a single-threaded build is deterministic.
            self._index.set_num_threads(1)
            self._index.set_ef(HNSW_SEARCH)
        # Row bands of the descriptor: band b averages rows band_edges[b]..band_edges[b + 1].
        self._band_edges = np.linspace(0, params.height, params.index_rows + 1).round().astype(int)

    def __len__(self) -> int:
        return len(self.frames)

    def template_of(self, image: np.ndarray) -> np.ndarray:
        """The normalised view template of an 8-bit grey or BGR image."""
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if image.ndim != 2 or image.size == 0:
            raise TemplateError(f"view template: expected a grey or BGR image, got shape {image.shape}")
        h, w = image.shape
        x0, x1, y0, y1 = self.params.crop
        crop = image[int(y0 * h):max(int(y1 * h), int(y0 * h) + 1), int(x0 * w):max(int(x1 * w), int(x0 * w) + 1)]
        patch = cv2.resize(crop.astype(np.float32) / 255.0, (self.params.width, self.params.height),
                           interpolation=cv2.INTER_AREA)
        mean = float(patch.mean())
        if self.params.normalisation > 0 and mean > 0:
            patch *= self.params.normalisation / mean
        return patch

    def observe(self, image: np.ndarray, frame: int, learn: bool = True) -> ViewMatch:
        """Match the frame's view against every stored template; store it when none is close
        (without ``learn``, a localisation: the closest is the match, however far)."""
        patch = self.template_of(image)
        nearest = -1
        if self.frames:
            template_id, distance, shift = self.best_match(patch)
            nearest = self.frames[template_id]
            if distance <= self.params.match_threshold or not learn:
                return ViewMatch(template_id, False, distance, shift * self.radians_per_column, nearest, shift, nearest)
        else:
            distance = 0.0
        template_id = self.add(patch, frame)
        return ViewMatch(template_id, True, distance, 0.0, frame, 0, nearest)

    def best_match(self, patch: np.ndarray) -> tuple[int, float, int]:
        """(template id, distance, shift) of the stored template closest to `patch`."""
        candidates = self._candidates(patch)
        distances = self._shifted_distances(patch[None, :, :], self._patches[candidates])   # (k, shifts)
        # The closest candidate; ties go to the oldest template, so a result never depends on
        # the order in which candidates were found.
        row = int(np.lexsort((candidates, distances.min(axis=1)))[0])
        column = int(np.argmin(distances[row]))
        return int(candidates[row]), float(distances[row, column]), column - self.params.shift_range

    def _candidates(self, patch: np.ndarray) -> np.ndarray:
        """Ids of the stored templates to compare exactly: all of them (exhaustive), or the
        union of each shift's nearest by descriptor."""
        count = len(self.frames)
        if self.params.matcher == "exhaustive" or count <= self.params.candidates:
            return np.arange(count)
        r, width = self.params.shift_range, self.params.width
        bands = self._bands(patch)
        queries = np.stack([bands[:, r + s:width - r + s].ravel() for s in range(-r, r + 1)])
        ids, _ = self._index.knn_query(queries, k=self.params.candidates)
        return np.unique(ids).astype(np.int64)

    def _bands(self, patch: np.ndarray) -> np.ndarray:
        """The patch's rows averaged into the descriptor's bands, (index_rows, width)."""
        return np.add.reduceat(patch, self._band_edges[:-1], axis=0) / np.diff(self._band_edges)[:, None]

    def _shifted_distances(self, current: np.ndarray, stored: np.ndarray) -> np.ndarray:
        """Mean absolute difference over the overlap at every shift s in ±shift_range, where a
        positive s compares current column c + s with stored column c; shape (templates, shifts)."""
        r, width = self.params.shift_range, self.params.width
        out = np.empty((stored.shape[0], 2 * r + 1), dtype=np.float32)
        for i, s in enumerate(range(-r, r + 1)):
            a = current[..., max(s, 0):width + min(s, 0)]
            b = stored[..., max(-s, 0):width - max(s, 0)]
            out[:, i] = np.abs(a - b).reshape(stored.shape[0], -1).mean(axis=1)
        return out

    def patch(self, template_id: int) -> np.ndarray:
        """The stored template `template_id` (a copy)."""
        return self._patches[template_id].copy()

    def add(self, patch: np.ndarray, frame: int) -> int:
        """Store a template (as made by template_of) seen at `frame`; returns its id."""
        count = len(self.frames)
        if count == self._patches.shape[0]:   # grow geometrically: amortised O(1) per template
            self._patches = np.concatenate([self._patches, np.empty_like(self._patches)])
            if self._index is not None:
                self._index.resize_index(len(self._patches))
        self._patches[count] = patch
        if self._index is not None:
            r = self.params.shift_range
            descriptor = self._bands(self._patches[count])[:, r:self.params.width - r]
            self._index.add_items(np.ascontiguousarray(descriptor, dtype=np.float32).reshape(1, -1), [count])
        self.frames.append(frame)
        return count
