"""View templates (RatSLAM's local view cells; Milford & Wyeth 2008, Ball et al. 2013).

A frame's view template is a crop of the grey image, resized (area averaging) to a small
patch and normalised. It is compared with every stored template at horizontal shifts within
±`shift_range` columns by the mean absolute difference over the overlapping columns; the best
shift gives the rotation between the views. When no stored template is within
`match_threshold`, the view becomes a new template.

Matching stays fast as templates accumulate: every stored template is kept in one contiguous
array, a column-mean profile of each is compared with the current profile at every shift, and
only the `candidates` best by profile are compared patch to patch. The profile comparison is
a squared distance over the overlap, ‖a‖² + ‖b‖² − 2a·b: the stored side's windowed sums of
squares are computed once per template when it is stored, so a frame costs one matrix product
(templates × width) · (width × shifts), a BLAS call, instead of a pass per shift. The profile
distance of the true match is small whenever its patch distance is, so this prefilter rarely
changes the answer (the unit tests compare it with the exhaustive search on random views and on
NuBot) while the exact comparison costs the same at 1k or 50k templates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from services.common.errors import ConfigError, DataError


class TemplateError(DataError):
    """An image the view templates cannot use."""


@dataclass(frozen=True)
class TemplateParams:
    crop: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)   # x0, x1, y0, y1 as fractions of the image
    width: int = 60                  # template columns
    height: int = 10                 # template rows
    normalisation: float = 0.4       # scale each template to this mean intensity (0: no scaling)
    shift_range: int = 5             # compare at column shifts within ±shift_range
    match_threshold: float = 0.085   # a view within this distance of a template matches it
    fov_deg: float = 53.0            # horizontal field of view of the whole image, for relative angles
    candidates: int = 32             # templates compared patch to patch after the profile prefilter

    def check(self) -> None:
        x0, x1, y0, y1 = self.crop
        rules = [("crop", 0 <= x0 < x1 <= 1 and 0 <= y0 < y1 <= 1), ("width", self.width > 2 * self.shift_range),
                 ("height", self.height >= 1), ("shift_range", self.shift_range >= 0),
                 ("match_threshold", self.match_threshold > 0), ("fov_deg", 0 < self.fov_deg <= 360),
                 ("candidates", self.candidates >= 1), ("normalisation", self.normalisation >= 0)]
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


class ViewTemplates:
    """Every stored template and the frame it was stored at."""

    def __init__(self, params: TemplateParams = TemplateParams()):
        params.check()
        self.params = params
        self._patches = np.empty((64, params.height, params.width), dtype=np.float32)
        self._profiles = np.empty((64, params.width), dtype=np.float32)
        # overlap[c, i] = 1 when stored column c is compared at shift i (see _shifted_distances)
        shifts = range(-params.shift_range, params.shift_range + 1)
        self._overlap = np.zeros((params.width, len(shifts)), dtype=np.float32)
        for i, s in enumerate(shifts):
            self._overlap[max(-s, 0):params.width - max(s, 0), i] = 1.0
        self._profile_energy = np.empty((64, len(shifts)), dtype=np.float32)   # Σ stored² over each overlap
        self.frames: list[int] = []
        crop_fraction = params.crop[1] - params.crop[0]
        self.radians_per_column = math.radians(params.fov_deg) * crop_fraction / params.width

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

    def observe(self, image: np.ndarray, frame: int) -> ViewMatch:
        """Match the frame's view against every stored template; store it when none is close."""
        patch = self.template_of(image)
        if self.frames:
            template_id, distance, shift = self.best_match(patch)
            if distance <= self.params.match_threshold:
                return ViewMatch(template_id, False, distance, shift * self.radians_per_column,
                                 self.frames[template_id], shift)
        else:
            distance = 0.0
        template_id = self.add(patch, frame)
        return ViewMatch(template_id, True, distance, 0.0, frame, 0)

    def best_match(self, patch: np.ndarray) -> tuple[int, float, int]:
        """(template id, distance, shift) of the stored template closest to `patch`."""
        count = len(self.frames)
        best_profile = self._profile_distances(patch.mean(axis=0)).min(axis=1)
        k = min(self.params.candidates, count)
        candidates = np.argpartition(best_profile, k - 1)[:k] if k < count else np.arange(count)
        distances = self._shifted_distances(patch[None, :, :], self._patches[candidates])   # (k, shifts)
        # The closest candidate; ties go to the oldest template, so a result never depends on
        # the order in which candidates were found.
        row = int(np.lexsort((candidates, distances.min(axis=1)))[0])
        column = int(np.argmin(distances[row]))
        return int(candidates[row]), float(distances[row, column]), column - self.params.shift_range

    def _profile_distances(self, profile: np.ndarray) -> np.ndarray:
        """Mean squared difference between the current column profile and every stored one over
        the overlap at every shift (the same overlaps as _shifted_distances); (templates, shifts)."""
        r, width = self.params.shift_range, self.params.width
        placed = np.zeros_like(self._overlap)   # column i: the current profile moved onto the stored columns of shift i
        for i, s in enumerate(range(-r, r + 1)):
            placed[max(-s, 0):width - max(s, 0), i] = profile[max(s, 0):width + min(s, 0)]
        count = len(self.frames)
        distances = self._profiles[:count] @ placed
        distances *= -2.0
        distances += self._profile_energy[:count]
        distances += (placed * placed).sum(axis=0)
        distances /= self._overlap.sum(axis=0)
        return distances

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
            self._profiles = np.concatenate([self._profiles, np.empty_like(self._profiles)])
            self._profile_energy = np.concatenate([self._profile_energy, np.empty_like(self._profile_energy)])
        self._patches[count] = patch
        self._profiles[count] = patch.mean(axis=0)
        self._profile_energy[count] = (self._profiles[count] ** 2) @ self._overlap
        self.frames.append(frame)
        return count
