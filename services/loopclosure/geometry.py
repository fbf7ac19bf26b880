"""Metric loop closures: the relative pose between the current frame and an earlier keyframe,
measured from the images, with its uncertainty (issue 11; docs/closure_geometry.md).

A *keyframe* is what a frame leaves for later closures: ORB features (Rublee et al., ICCV 2011)
of its left image, spread over the image, and, for a stereo frame, their disparity in the right
image, found by pyramidal Lucas–Kanade along the epipolar row (as services/egomotion/stereo.py
does), which places each feature in 3D in the keyframe's camera frame. No image is kept.

When a closure is confirmed, the current left image's ORB features are matched to the
keyframe's (Hamming distance, Lowe's ratio test, one keyframe feature per current feature) and

- **stereo** (the keyframe has 3D points): the current camera's pose comes from PnP with RANSAC
  on the 3D–2D matches, refined by Levenberg–Marquardt (cv2.solvePnPRefineLM) and then by
  Gauss–Newton steps weighted by each match's modelled error: a pixel noise in the image plus
  the keyframe point's depth error along its ray (a disparity noise, which dominates for far
  points). The covariance of the 6-DoF pose is s²(JᵀWJ)⁻¹ (J: the reprojection Jacobian of
  cv2.projectPoints, W: the matches' inverse error covariances, s²: the weighted residual
  variance χ²/(2n − 6), the a-posteriori variance factor), propagated to the planar
  (forward, left, yaw) by a numerical Jacobian, plus floors.
- **mono** (no 3D points): the essential matrix of a horizontal translation (a ground robot
  does not change height between visits) and a free rotation, fitted to the matches' Sampson
  errors by profiling the direction of the translation over 180° (see "Monocular closures"
  below for why the general five-parameter fit is not used); the covariance of (direction,
  yaw) is the likelihood-weighted spread of that profile. The translation's length is not
  observable: (forward, left) is the unit direction of the translation, ``scaled`` is False,
  and the map takes the length from the odometry.

Conventions (services/common/geometry.py): camera x right, y down, z forward; body x forward,
y left, yaw counter-clockwise. ``RelativePose`` is the current frame's body pose in the
keyframe's body frame: keyframe_pose ∘ (forward, left, yaw) = current_pose.

Nothing here raises for a poor image (blank, blurred, another place): the result is
``ok=False`` with a one-phrase reason. A keyframe is quantised when it is made exactly as it is
stored (``Keyframe.to_bytes``), so a keyframe read back after a restart gives the same
relative poses as the one kept in memory.
"""

from __future__ import annotations

import functools
import logging
import math
import struct
from dataclasses import dataclass

import cv2
import numpy as np

from services.common.errors import ConfigError, DataError
from services.common.features import TrackParams, track
from services.common.frames import Camera
from services.common.geometry import increment_from_transform, invert_transform, transform_from_rt
from services.common.images import grey
from services.common.settings import setting

log = logging.getLogger(__name__)


class KeyframeError(DataError):
    """Bytes that are not a keyframe of a known version (the message says what is wrong)."""


@dataclass(frozen=True)
class GeometryParams:
    """Parameters of keyframes and closure geometry; the defaults suit a user's own camera at
    320×240 to 1280×720 (nothing in them is tuned to one dataset)."""

    features: int = setting(200, help="features kept per keyframe (each costs 38 bytes stored)")
    query_features: int = setting(500, help="features detected in the current image of a closure")
    grid: tuple[int, int] = setting((8, 6), help="columns, rows of the cells over which features are spread")
    pyramid_levels: int = setting(4, help="ORB scales (1.2 apart: 1.7× of scale change across them)")
    fast_threshold: int = setting(20, help="ORB's FAST threshold, grey levels (ORB's default)")
    ratio: float = setting(0.8, help="Lowe's ratio test on Hamming distances")
    max_distance: int = setting(80, help="largest Hamming distance of a match (of 256 bits)")
    # Stereo keyframes: left–right matching along the row (services/egomotion/stereo.py).
    stereo_window_px: int = setting(11, help="stereo keyframes: Lucas–Kanade window of the left–right match, px")
    stereo_pyramid_levels: int = setting(4, help="stereo keyframes: pyramid levels of the left–right match")
    stereo_candidates: int = setting(300, help="keypoints tried in the right image (the first `features` found are kept)")
    stereo_forward_backward_px: float = setting(
        0.0, help="backward check of the left–right match, px (0: none; the row check rejects most bad matches)")
    max_row_error_px: float = setting(1.0, help="stereo keyframes: largest row difference of a left–right match, px")
    min_disparity_px: float = setting(0.5, help="stereo keyframes: smallest disparity, px")
    # Pose: stereo RANSAC (reprojection error), mono inlier threshold (Sampson error), support.
    ransac_px: float = setting(3.0, help="stereo PnP RANSAC: reprojection error of an inlier, px")
    ransac_iterations: int = setting(500, help="stereo PnP RANSAC iterations")
    mono_threshold_px: float = setting(1.5, help="mono: Sampson error of an inlier, px")
    min_inliers: int = setting(20, help="inliers a relative pose needs")
    min_inlier_ratio: float = setting(0.3, help="inliers / matches a relative pose needs")
    min_parallax_px: float = setting(1.0, help="mono: below it the direction of the translation is unknown, px")
    # Plausibility: a closure is between two views of one place.
    max_translation_m: float = setting(5.0, help="plausibility: largest translation between the views, m")
    max_yaw_deg: float = setting(60.0, help="plausibility: largest yaw between the views, degrees")
    max_tilt_deg: float = setting(10.0, help="plausibility: largest pitch and roll between the views, degrees")
    max_height_m: float = setting(0.5, help="plausibility, stereo: largest change of the camera's height, m")
    # Error model (stereo) and covariance floors (added to the diagonal).
    pixel_sigma: float = setting(0.7, help="stereo error model: feature position noise, px (only its ratio to "
                                           "disparity_sigma matters)")
    disparity_sigma: float = setting(0.2, help="stereo error model: disparity noise, px")
    floor_translation_m: float = setting(0.005, help="covariance floor of the translation, m")
    floor_yaw_deg: float = setting(0.1, help="covariance floor of the yaw, degrees")
    floor_direction_deg: float = setting(1.0, help="mono: covariance floor of the translation's direction, degrees")

    def check(self) -> None:
        """Raise ConfigError naming the first invalid parameter."""
        rules = [
            ("features", 8 <= self.features <= 65535), ("query_features", self.query_features >= 8),
            ("grid", len(self.grid) == 2 and min(self.grid) >= 1), ("pyramid_levels", 1 <= self.pyramid_levels <= 8),
            ("fast_threshold", 1 <= self.fast_threshold <= 255), ("ratio", 0 < self.ratio <= 1),
            ("max_distance", 0 < self.max_distance <= 256), ("stereo_window_px", self.stereo_window_px >= 3),
            ("stereo_pyramid_levels", self.stereo_pyramid_levels >= 0),
            ("stereo_candidates", self.stereo_candidates >= 1), ("stereo_forward_backward_px", self.stereo_forward_backward_px >= 0),
            ("max_row_error_px", self.max_row_error_px > 0),
            ("min_disparity_px", self.min_disparity_px > 0), ("ransac_px", self.ransac_px > 0),
            ("ransac_iterations", self.ransac_iterations >= 1), ("mono_threshold_px", self.mono_threshold_px > 0),
            ("min_inliers", self.min_inliers >= 6), ("min_inlier_ratio", 0 <= self.min_inlier_ratio <= 1),
            ("min_parallax_px", self.min_parallax_px >= 0), ("max_translation_m", self.max_translation_m > 0),
            ("max_yaw_deg", 0 < self.max_yaw_deg <= 180), ("max_tilt_deg", 0 < self.max_tilt_deg <= 180),
            ("max_height_m", self.max_height_m > 0),
            ("pixel_sigma", self.pixel_sigma > 0), ("disparity_sigma", self.disparity_sigma > 0),
            ("floor_translation_m", self.floor_translation_m >= 0), ("floor_yaw_deg", self.floor_yaw_deg >= 0),
            ("floor_direction_deg", self.floor_direction_deg >= 0),
        ]
        for name, ok in rules:
            if not ok:
                raise ConfigError(f"closure geometry: invalid {name} = {getattr(self, name)!r}")


# ---------------------------------------------------------------------------------------------
# Keyframes

_HEADER = struct.Struct("<BBHHHBB")   # version, flags, count, width, height, keypoint bits, descriptor bytes
_CAMERA = struct.Struct("<5d")       # fx, fy, cx, cy, baseline
_VERSION = 1
_HAS_CAMERA, _HAS_DISPARITY = 1, 2
DISPARITY_STEP = 1 / 64              # px: stored disparities are multiples of it (≤ 1023.98 px)


@dataclass(frozen=True, eq=False)
class Keyframe:
    """What a frame keeps for later closures (no image).

    ``keypoints`` (N, 2) float32 pixel positions in the left image, ``descriptors`` (N, D) uint8
    (ORB: D = 32), ``disparity`` (N,) float32 pixels in the right image, NaN where the feature
    has no depth, or None for a monocular keyframe; ``camera`` the left camera's intrinsics and
    baseline (width, height: the image's), or None when it was not calibrated; ``image_size``
    (width, height) of the left image.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    disparity: np.ndarray | None
    camera: Camera | None
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return len(self.keypoints)

    @functools.cached_property
    def points(self) -> np.ndarray | None:
        """(N, 3) float64 positions in the keyframe's camera frame (x right, y down, z forward),
        NaN rows where a feature has no depth; None without disparities or a stereo camera:
        Z = fx·b/d, X = (u − cx)·Z/fx, Y = (v − cy)·Z/fy."""
        camera = self.camera
        if self.disparity is None or camera is None or camera.baseline <= 0:
            return None
        depth = camera.fx * camera.baseline / self.disparity.astype(np.float64)
        u, v = self.keypoints[:, 0].astype(np.float64), self.keypoints[:, 1].astype(np.float64)
        return np.column_stack(((u - camera.cx) * depth / camera.fx, (v - camera.cy) * depth / camera.fy, depth))

    @property
    def depth_count(self) -> int:
        """Features with a 3D point."""
        return 0 if self.points is None else int(np.isfinite(self.disparity).sum())

    def to_bytes(self) -> bytes:
        """Compact, versioned bytes: a 10-byte header, the camera (40 bytes), keypoints as
        uint16 multiples of 2^-k px (k as fine as the image size allows: 1/64 px at 640×480),
        the descriptors, and disparities as uint16 multiples of 1/64 px (0: no depth). The
        rounding (≤ 1/128 px) is far below the features' own noise (tenths of a pixel)."""
        count, descriptor_bytes = self.descriptors.shape if len(self.descriptors) else (0, 32)
        image_w, image_h = self.image_size
        bits = _keypoint_bits(image_w, image_h)
        flags = (_HAS_CAMERA if self.camera is not None else 0) | (_HAS_DISPARITY if self.disparity is not None else 0)
        parts = [_HEADER.pack(_VERSION, flags, count, image_w, image_h, bits, descriptor_bytes)]
        if self.camera is not None:
            c = self.camera
            parts.append(_CAMERA.pack(c.fx, c.fy, c.cx, c.cy, c.baseline))
        parts.append(np.round(self.keypoints.astype(np.float64) * (1 << bits)).astype("<u2").tobytes())
        parts.append(np.ascontiguousarray(self.descriptors, dtype=np.uint8).tobytes())
        if self.disparity is not None:
            steps = np.round(np.nan_to_num(self.disparity.astype(np.float64), nan=0.0) / DISPARITY_STEP)
            parts.append(np.clip(steps, 0, 65535).astype("<u2").tobytes())
        return b"".join(parts)

    @classmethod
    def from_bytes(cls, data: bytes) -> Keyframe:
        """The keyframe `to_bytes` wrote; KeyframeError for anything else."""
        if len(data) < _HEADER.size:
            raise KeyframeError(f"keyframe: {len(data)} bytes, shorter than its header")
        version, flags, count, image_w, image_h, bits, descriptor_bytes = _HEADER.unpack_from(data)
        if version != _VERSION:
            raise KeyframeError(f"keyframe: unknown version {version} (this build reads version {_VERSION})")
        if bits > 15:
            raise KeyframeError(f"keyframe: keypoint precision 2^-{bits} px is out of range")
        camera_size = _CAMERA.size if flags & _HAS_CAMERA else 0
        expected = _HEADER.size + camera_size + count * (4 + descriptor_bytes + (2 if flags & _HAS_DISPARITY else 0))
        if len(data) != expected:
            raise KeyframeError(f"keyframe: {len(data)} bytes where its header announces {expected}")
        offset = _HEADER.size
        camera = None
        if flags & _HAS_CAMERA:
            fx, fy, cx, cy, baseline = _CAMERA.unpack_from(data, offset)
            camera = Camera(fx, fy, cx, cy, baseline, image_w, image_h)
            offset += camera_size
        keypoints = np.frombuffer(data, "<u2", 2 * count, offset).reshape(count, 2).astype(np.float32) / np.float32(1 << bits)
        offset += 4 * count
        descriptors = np.frombuffer(data, np.uint8, count * descriptor_bytes, offset).reshape(count, descriptor_bytes).copy()
        offset += count * descriptor_bytes
        disparity = None
        if flags & _HAS_DISPARITY:
            steps = np.frombuffer(data, "<u2", count, offset).astype(np.float32)
            disparity = np.where(steps > 0, steps * np.float32(DISPARITY_STEP), np.float32(np.nan)).astype(np.float32)
        return cls(keypoints, descriptors, disparity, camera, (image_w, image_h))


def _keypoint_bits(width: int, height: int) -> int:
    """Fraction bits of stored keypoints: the finest 2^-k px grid whose range covers the image."""
    largest = max(width, height, 1)
    return max(0, min(8, int(math.floor(math.log2(65535 / largest)))))


# ---------------------------------------------------------------------------------------------
# Relative poses


@dataclass(frozen=True, eq=False)
class Features:
    """A frame's ORB features: ``keypoints`` (N, 2) float32 pixels, ``descriptors`` (N, 32)
    uint8, ``image_size`` (width, height)."""

    keypoints: np.ndarray
    descriptors: np.ndarray
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return len(self.keypoints)


@dataclass(frozen=True, eq=False)
class RelativePose:
    """The current frame's body pose in the keyframe's body frame, or why there is none.

    ``method`` "stereo" or "mono". Stereo: forward, left in metres, yaw in radians, and
    ``covariance`` the 3×3 covariance of (forward, left, yaw). Mono (``scaled`` False):
    (forward, left) is the unit vector of the planar translation's direction and ``covariance``
    the covariance of (forward, left, yaw) *of that unit vector*: for a direction angle known to
    σθ the (forward, left) block is σθ²·n nᵀ with n = (−left, forward), singular along the
    direction since its length is not measured; when the views show too little parallax to tell
    the direction, (forward, left) = (0, 0) and that block is I/2 (a direction equally likely
    anywhere). ``inliers`` counts the matches that support the pose (0 when none was found).
    """

    ok: bool
    reason: str
    method: str
    forward: float
    left: float
    yaw: float
    covariance: np.ndarray
    inliers: int
    scaled: bool


def _failure(method: str, reason: str, inliers: int = 0) -> RelativePose:
    return RelativePose(False, reason, method, 0.0, 0.0, 0.0, np.full((3, 3), np.nan), int(inliers), method == "stereo")


class ClosureGeometry:
    """Keyframes of new view templates and relative poses of confirmed closures (module docstring)."""

    def __init__(self, params: GeometryParams = GeometryParams()):
        params.check()
        self.params = params
        detect = dict(scaleFactor=1.2, nlevels=params.pyramid_levels, fastThreshold=params.fast_threshold)
        # Detection asks for a few times the features kept: the spread over the grid picks from them.
        self._keyframe_orb = cv2.ORB_create(nfeatures=4 * params.features, **detect)
        self._query_orb = cv2.ORB_create(nfeatures=3 * params.query_features, **detect)
        self._stereo_track = TrackParams(params.stereo_window_px, params.stereo_pyramid_levels,
                                         params.stereo_forward_backward_px)

    # -- keyframes

    def keyframe(self, left: np.ndarray, right: np.ndarray | None = None, camera: Camera | None = None) -> Keyframe:
        """The keyframe of a frame: stereo (features with depth only) when ``right`` is given
        and ``camera`` has a baseline, else monocular. A blank image gives an empty keyframe."""
        p = self.params
        left = grey(left)
        height, width = left.shape
        stereo = right is not None and camera is not None and camera.baseline > 0
        keypoints = _spread_keypoints(self._keyframe_orb, left, p.grid)
        disparity = None
        if stereo:
            right = grey(right)
            if right.shape != left.shape:
                raise ConfigError(f"closure geometry: left {left.shape} and right {right.shape} images differ in size")
            chosen, disparity = self._stereo(left, right, np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2))
            keypoints, disparity = [keypoints[i] for i in chosen[:p.features]], disparity[:p.features]
        keypoints, descriptors, described = _describe(self._keyframe_orb, left, keypoints[:p.features])
        if disparity is not None:
            disparity = disparity[described]
        if camera is not None:
            camera = Camera(camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline if stereo else 0.0, width, height)
        made = Keyframe(keypoints, descriptors, disparity, camera, (width, height))
        return Keyframe.from_bytes(made.to_bytes())   # exactly what the store will give back

    def _stereo(self, left: np.ndarray, right: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Which of the keypoints ``xy`` (in spread order, the first ``stereo_candidates``) match
        along their row in the right image (indices into ``xy``), and their disparities."""
        p = self.params
        xy = np.ascontiguousarray(xy[:p.stereo_candidates], dtype=np.float32)
        if len(xy) == 0:
            return np.empty(0, int), np.empty(0, np.float32)
        matched, good = track(left, right, xy, self._stereo_track, xy)
        disparity = xy[:, 0] - matched[:, 0]
        good &= (np.abs(xy[:, 1] - matched[:, 1]) <= p.max_row_error_px) & (disparity >= p.min_disparity_px)
        good &= disparity < 65535 * DISPARITY_STEP
        keep = np.flatnonzero(good)
        return keep, disparity[keep].astype(np.float32)

    # -- relative poses

    def features(self, left: np.ndarray) -> Features:
        """The current frame's features for matching against keyframes: the first
        ``query_features`` ORB features of its left image, spread over the grid."""
        left = grey(left)
        keypoints, descriptors, _ = _describe(self._query_orb, left,
                                              _spread_keypoints(self._query_orb, left, self.params.grid)[:self.params.query_features])
        return Features(keypoints, descriptors, (left.shape[1], left.shape[0]))

    def verify(self, keyframe: Keyframe, features: Features) -> int:
        """How many of the frame's features match the keyframe's consistently with one rigid
        motion of a camera between two views of a scene: the inliers of a fundamental matrix
        fitted by RANSAC (``ransac_px``) to the matches that pass the ratio test. It needs no
        calibration; two views of different places leave only chance inliers (around ten)."""
        if len(keyframe) < 8 or len(features) < 8 or tuple(keyframe.image_size) != features.image_size:
            return 0
        first, second = self._match(keyframe.descriptors, features.descriptors, np.ones(len(keyframe), bool))
        if len(first) < 8:
            return 0
        try:
            F, inliers = cv2.findFundamentalMat(keyframe.keypoints[first], features.keypoints[second], cv2.FM_RANSAC,
                                                self.params.ransac_px, 0.99, self.params.ransac_iterations)
        except cv2.error:
            return 0
        return 0 if F is None or inliers is None else int(np.count_nonzero(inliers))

    def relative_pose(self, keyframe: Keyframe, left: np.ndarray, camera: Camera | None = None,
                      features: Features | None = None) -> RelativePose:
        """The pose of the frame whose left image is ``left`` relative to ``keyframe`` (stereo
        when the keyframe has 3D points, else mono); ``camera`` defaults to the keyframe's;
        ``features``: the frame's, when already found (``features(left)``)."""
        p = self.params
        stereo = keyframe.points is not None
        method = "stereo" if stereo else "mono"
        camera = camera or keyframe.camera
        if camera is None:
            return _failure(method, "no camera calibration")
        features = features or self.features(left)
        if features.image_size != tuple(keyframe.image_size):
            return _failure(method, f"image size {features.image_size[0]}×{features.image_size[1]} differs from the "
                                    f"keyframe's {keyframe.image_size[0]}×{keyframe.image_size[1]}")
        usable = keyframe.depth_count if stereo else len(keyframe)
        if usable < p.min_inliers:
            return _failure(method, f"keyframe has too few features ({usable} < {p.min_inliers})")
        keypoints, descriptors = features.keypoints, features.descriptors
        if len(keypoints) < p.min_inliers:
            return _failure(method, f"too few features ({len(keypoints)} < {p.min_inliers})")
        usable = np.isfinite(keyframe.disparity) if stereo else np.ones(len(keyframe), bool)
        first, second = self._match(keyframe.descriptors, descriptors, usable)
        if len(first) < p.min_inliers:
            return _failure(method, f"too few matches ({len(first)} < {p.min_inliers})")
        K = camera.matrix()
        if stereo:
            fb = keyframe.camera.fx * keyframe.camera.baseline
            return self._stereo_pose(keyframe.points[first], keypoints[second].astype(np.float64), K, fb)
        return self._mono_pose(keyframe.keypoints[first].astype(np.float64), keypoints[second].astype(np.float64), K)

    def _match(self, stored: np.ndarray, current: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices (keyframe, current) of matches passing the ratio test, at most one per
        current feature (the closest)."""
        p = self.params
        candidates = np.flatnonzero(usable)
        if len(candidates) == 0:
            return np.empty(0, int), np.empty(0, int)
        # The two nearest current features of each usable keyframe feature (OpenCV's brute-force
        # search, as BFMatcher's knnMatch, without a DMatch object per pair).
        k = min(2, len(current))
        if k == 0:
            return np.empty(0, int), np.empty(0, int)
        distances, nearest = cv2.batchDistance(stored[candidates], current, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=k)
        best = distances[:, 0]
        good = best <= p.max_distance
        if k > 1:
            good &= best < p.ratio * distances[:, 1]
        first, second, distance = candidates[good], nearest[good, 0].astype(int), best[good]
        if len(first) == 0:
            return np.empty(0, int), np.empty(0, int)
        order = np.lexsort((distance, second))
        keep = order[np.r_[True, second[order][1:] != second[order][:-1]]]   # closest per current feature
        return first[keep], second[keep]

    def _stereo_pose(self, points: np.ndarray, pixels: np.ndarray, K: np.ndarray, fb: float) -> RelativePose:
        p = self.params
        try:
            found, rvec, tvec, inliers = cv2.solvePnPRansac(
                points, pixels, K, None, iterationsCount=p.ransac_iterations, reprojectionError=p.ransac_px,
                confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
        except cv2.error as error:
            log.debug("closure geometry: PnP failed: %s", error)
            found = False
        if not found or inliers is None or len(inliers) < p.min_inliers:
            count = 0 if not found or inliers is None else len(inliers)
            return _failure("stereo", f"too few inliers ({count} < {p.min_inliers})", count)
        inlier = np.zeros(len(points), bool)
        inlier[inliers.ravel()] = True
        rvec, tvec = cv2.solvePnPRefineLM(points[inlier], pixels[inlier], K, None, rvec, tvec)
        projected, _ = cv2.projectPoints(points, rvec, tvec, K, None)
        inlier = np.linalg.norm(projected.reshape(-1, 2) - pixels, axis=1) < p.ransac_px
        count = int(inlier.sum())
        if count < p.min_inliers:
            return _failure("stereo", f"too few inliers ({count} < {p.min_inliers})", count)
        if count < p.min_inlier_ratio * len(points):
            return _failure("stereo", f"too few inliers ({count} of {len(points)} matches)", count)
        rvec, tvec, covariance6 = self._weighted_refinement(points[inlier], pixels[inlier], K, fb, rvec, tvec)
        if covariance6 is None:
            return _failure("stereo", "degenerate geometry", count)
        transform = transform_from_rt(rvec, tvec)
        reason = self._implausible(transform)
        if reason:
            return _failure("stereo", reason, count)
        forward, left, yaw = increment_from_transform(transform)
        G = _planar_jacobian(lambda x: increment_from_transform(transform_from_rt(x[:3], x[3:])),
                             np.concatenate([rvec.ravel(), tvec.ravel()]))
        covariance = G @ covariance6 @ G.T + np.diag([p.floor_translation_m ** 2, p.floor_translation_m ** 2,
                                                      math.radians(p.floor_yaw_deg) ** 2])
        return RelativePose(True, "", "stereo", forward, left, yaw, covariance, count, True)

    def _weighted_refinement(self, points, pixels, K, fb, rvec, tvec):
        """Gauss–Newton steps minimising the reprojection errors weighted by their modelled
        covariances, and the pose covariance s²(JᵀWJ)⁻¹ (module docstring); None when singular."""
        p = self.params
        rvec, tvec = rvec.reshape(3, 1).astype(np.float64), tvec.reshape(3, 1).astype(np.float64)
        n = len(points)
        for step in range(3):   # two steps, then the Jacobian and residuals at the result
            projected, jacobian = cv2.projectPoints(points, rvec, tvec, K, None)
            residual = projected.reshape(n, 2) - pixels
            J = jacobian[:, :6].reshape(n, 2, 6)
            weight = _match_weights(points, rvec, tvec, K, fb, p.pixel_sigma, p.disparity_sigma)
            JtW = np.einsum("nki,nkl->nil", J, weight)        # (n, 6, 2)
            information = np.einsum("nil,nlj->ij", JtW, J)
            if not np.all(np.isfinite(information)) or np.linalg.cond(information) > 1e12:
                return rvec, tvec, None
            if step < 2:
                delta = np.linalg.solve(information, -np.einsum("nil,nl->i", JtW, residual))
                rvec, tvec = rvec + delta[:3, None], tvec + delta[3:, None]
        chi2 = float(np.einsum("nk,nkl,nl->", residual, weight, residual))
        return rvec, tvec, chi2 / max(2 * n - 6, 1) * np.linalg.inv(information)

    def _mono_pose(self, first: np.ndarray, second: np.ndarray, K: np.ndarray) -> RelativePose:
        p = self.params
        K_inv = np.linalg.inv(K)
        x1 = np.column_stack((first, np.ones(len(first)))) @ K_inv.T
        x2 = np.column_stack((second, np.ones(len(second)))) @ K_inv.T
        fit = _mono_fit(x1, x2, K, p.mono_threshold_px)
        if fit is None:
            return _failure("mono", "degenerate geometry")
        rotation, direction, covariance2, inlier = fit
        count = int(inlier.sum())
        if count < p.min_inliers:
            return _failure("mono", f"too few inliers ({count} < {p.min_inliers})", count)
        if count < p.min_inlier_ratio * len(first):
            return _failure("mono", f"too few inliers ({count} of {len(first)} matches)", count)
        x1, x2 = x1[inlier], x2[inlier]
        transform = np.eye(4)
        transform[:3, :3] = rotation
        reason = self._implausible(transform)
        if reason:
            return _failure("mono", reason, count)
        yaw = _yaw_of(rotation)
        yaw_variance = covariance2[1, 1] + math.radians(p.floor_yaw_deg) ** 2
        if _parallax(x1, x2, K, rotation) < p.min_parallax_px:
            # A rotation explains the views: the direction of the translation is unknown.
            return RelativePose(True, "", "mono", 0.0, 0.0, yaw, np.diag([0.5, 0.5, yaw_variance]), count, False)
        direction = _cheiral(x1, x2, rotation, direction)
        forward, left = math.cos(direction), math.sin(direction)
        J = np.array([[-left, 0.0], [forward, 0.0], [0.0, 1.0]])   # (forward, left, yaw) per (direction, yaw)
        covariance = J @ covariance2 @ J.T
        covariance[:2, :2] += math.radians(p.floor_direction_deg) ** 2 * np.outer([-left, forward], [-left, forward])
        covariance[2, 2] += math.radians(p.floor_yaw_deg) ** 2
        return RelativePose(True, "", "mono", forward, left, yaw, covariance, count, False)

    def _implausible(self, transform: np.ndarray) -> str:
        """Why a measured transform cannot be a closure between two views of one place ('' if it can)."""
        p = self.params
        motion = invert_transform(transform)   # the current camera in the keyframe's camera frame
        yaw = math.degrees(abs(increment_from_transform(transform)[2]))
        tilt = math.degrees(math.acos(min(1.0, abs(float(motion[1, 1])))))   # angle between the down axes
        distance = float(np.linalg.norm(motion[:3, 3]))
        height = abs(float(motion[1, 3]))
        if yaw > p.max_yaw_deg:
            return f"implausible yaw ({yaw:.0f}° > {p.max_yaw_deg:g}°)"
        if tilt > p.max_tilt_deg:
            return f"implausible tilt ({tilt:.0f}° > {p.max_tilt_deg:g}°)"
        if distance > p.max_translation_m:
            return f"implausible translation ({distance:.1f} m > {p.max_translation_m:g} m)"
        if height > p.max_height_m:
            return f"implausible height change ({height:.2f} m > {p.max_height_m:g} m)"
        return ""


# ---------------------------------------------------------------------------------------------
# Helpers


def _spread_keypoints(orb, image: np.ndarray, grid: tuple[int, int]) -> list:
    """The ORB keypoints of ``image`` ordered so that they spread over a grid of cells: the
    strongest of every cell first, then the second strongest of every cell, and so on
    (LIBVISO2-style bucketing without a cap per cell, so that a scene textured in one corner
    still gives as many); a prefix of the list is a spread-out selection."""
    keypoints = orb.detect(image, None)
    if not keypoints:
        return []
    xy = np.array([k.pt for k in keypoints], dtype=np.float64)
    response = np.array([k.response for k in keypoints])
    height, width = image.shape
    columns, rows = grid
    cell = (np.minimum(xy[:, 1] * rows // height, rows - 1) * columns
            + np.minimum(xy[:, 0] * columns // width, columns - 1)).astype(np.int64)
    order = np.lexsort((-response, cell))
    sorted_cell = cell[order]
    rank = np.arange(len(order)) - np.searchsorted(sorted_cell, sorted_cell, side="left")
    return [keypoints[i] for i in order[np.lexsort((-response[order], rank))]]


def _describe(orb, image: np.ndarray, keypoints: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (N, 2) float32 and ORB descriptors (N, 32) uint8 of ``keypoints``, and the
    index of each in ``keypoints`` (ORB leaves out a keypoint it cannot describe)."""
    for index, keypoint in enumerate(keypoints):
        keypoint.class_id = index
    kept, descriptors = orb.compute(image, keypoints) if keypoints else ((), None)
    if descriptors is None or not kept:
        return np.empty((0, 2), np.float32), np.empty((0, 32), np.uint8), np.empty(0, int)
    return (np.array([k.pt for k in kept], dtype=np.float32), descriptors,
            np.array([k.class_id for k in kept], dtype=int))


def _match_weights(points, rvec, tvec, K, fb: float, pixel_sigma: float, disparity_sigma: float) -> np.ndarray:
    """(n, 2, 2) inverse covariances of the reprojection errors: pixel noise σp² I plus the
    keyframe point's depth error along its ray, g gᵀ σd² with g the image motion of the
    projection per pixel of keyframe disparity d = fx·b/Z (X ∝ 1/d, so ∂X/∂d = −X/d)."""
    R = cv2.Rodrigues(rvec)[0]
    camera_points = points @ R.T + tvec.reshape(1, 3)
    x, y, z = camera_points.T
    fx, fy = K[0, 0], K[1, 1]
    projection = np.zeros((len(points), 2, 3))   # ∂π/∂X in the current camera
    projection[:, 0, 0] = fx / z
    projection[:, 0, 2] = -fx * x / z ** 2
    projection[:, 1, 1] = fy / z
    projection[:, 1, 2] = -fy * y / z ** 2
    ray = -(points @ R.T) * (points[:, 2:3] / fb)   # ∂X/∂d = −X/d, rotated into the current camera
    g = np.einsum("nij,nj->ni", projection, ray)
    covariance = np.einsum("ni,nj->nij", g, g) * disparity_sigma ** 2
    covariance[:, 0, 0] += pixel_sigma ** 2
    covariance[:, 1, 1] += pixel_sigma ** 2
    return np.linalg.inv(covariance)


def _planar_jacobian(function, x: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """3×len(x) central-difference Jacobian of (forward, left, yaw) = function(x), yaw wrapped."""
    columns = []
    for i in range(len(x)):
        offset = np.zeros(len(x))
        offset[i] = step
        plus, minus = np.array(function(x + offset)), np.array(function(x - offset))
        difference = plus - minus
        difference[2] = math.remainder(difference[2], 2 * math.pi)
        columns.append(difference / (2 * step))
    return np.column_stack(columns)


# Monocular closures. The translation's length is not observable, and the general five-degree
# essential matrix is poorly conditioned at closures: the views are close and indoor scenes have
# little depth range, so yaw and the direction of the translation trade off along a long, curved
# valley of near-equal costs with shallow local minima, where the curvature at the minimum
# understates the spread many times over (docs/closure_geometry.md). A
# ground robot does not change height between its visits, so the translation is taken
# horizontal in the keyframe's camera frame, at an angle θ = atan2(left, forward), and the cost
# (truncated squared Sampson errors) is profiled over θ: on a grid over 180° (θ and θ + π fit
# the same matches; cheirality picks one) the rotation (yaw, and the small pitch and roll of an
# uneven floor) is fitted by Gauss–Newton at every θ; the lowest θ is refined on a finer grid,
# and the covariance of (θ, yaw) is the second moment about it of the profile weighted by its
# likelihood exp(−Δcost / 2s²) (s²: the minimum's cost per degree of freedom), plus each slice's
# own yaw variance and the grid's rounding.

_PROFILE_STEP_DEG = 3.0


def _rotations(vectors: np.ndarray) -> np.ndarray:
    """Rotation matrices (H, 3, 3) of rotation vectors (H, 3) (Rodrigues' formula)."""
    angle = np.linalg.norm(vectors, axis=1)
    axis = vectors / np.where(angle > 0, angle, 1.0)[:, None]
    cross = np.zeros((len(vectors), 3, 3))
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    cross -= cross.transpose(0, 2, 1)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * cross + (1 - c) * (cross @ cross)


def _centres(direction: np.ndarray) -> np.ndarray:
    """Unit horizontal positions (H, 3) in the keyframe's camera frame at angles ``direction``
    (forward = z, left = −x)."""
    return np.column_stack((-np.sin(direction), np.zeros(len(direction)), np.cos(direction)))


def _sampson(rotation: np.ndarray, centre: np.ndarray, x1: np.ndarray, x2: np.ndarray, focal: tuple[float, float]) -> np.ndarray:
    """Signed Sampson distances (H, N), in pixels, of normalised matches x1, x2 (N, 3) to the
    motions p_cur = R (p_kf − c) for rotations (H, 3, 3) and camera centres (H, 3): E = [t]×R with
    t = −R c, numerator x2ᵀEx1, gradients Ex1 and Eᵀx2 in pixels (divided by the focal lengths)."""
    t = -np.einsum("hij,hj->hi", rotation, centre)
    cross = np.zeros_like(rotation)
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
    cross -= cross.transpose(0, 2, 1)
    E = cross @ rotation
    Ex1 = x1 @ E.transpose(0, 2, 1)       # (H, N, 3)
    Etx2 = x2 @ E[:, :, :2]                # (H, N, 2): the first two components of Eᵀx2
    numerator = Ex1[..., 0] * x2[:, 0] + Ex1[..., 1] * x2[:, 1] + Ex1[..., 2]
    fx, fy = focal
    denominator = np.sqrt((Ex1[..., 0] ** 2 + Etx2[..., 0] ** 2) / fx ** 2 + (Ex1[..., 1] ** 2 + Etx2[..., 1] ** 2) / fy ** 2)
    return numerator / np.maximum(denominator, 1e-15)


def _yaw_rotation(yaw: float) -> np.ndarray:
    """The rotation of p_cur = R p_kf when the camera turns by ``yaw`` counter-clockwise (about −y)."""
    return _rotations(np.array([[0.0, yaw, 0.0]]))[0]


def _mono_fit(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, threshold: float):
    """(rotation, direction θ, covariance of (θ, yaw), inlier mask), θ modulo π; None when
    degenerate (see the comment above)."""
    focal = (K[0, 0], K[1, 1])
    start = _yaw_rotation(_yaw_only(x1, x2))
    step = math.radians(_PROFILE_STEP_DEG)
    directions = np.arange(-math.pi / 2 + step / 2, math.pi / 2, step)
    rotations, cost, yaw_variance, _ = _profile(x1, x2, focal, start, directions, threshold)
    best = int(np.argmin(cost))
    fine = directions[best] + np.linspace(-step, step, 11)
    fine_rotations, fine_cost, _, fine_inliers = _profile(x1, x2, focal, rotations[best], fine, threshold)
    pick = int(np.argmin(fine_cost))
    rotation, direction, minimum, inlier = fine_rotations[pick], float(fine[pick]), float(fine_cost[pick]), fine_inliers[pick]
    count = int(inlier.sum())
    variance = minimum / max(count - 4, 1)
    if count < 5 or not np.isfinite(variance) or variance <= 0 or not np.all(np.isfinite(cost)):
        return None
    yaw = _yaw_of(rotation)
    weight = np.exp(-np.maximum(cost - minimum, 0.0) / (2 * variance))
    weight /= weight.sum()
    yaws = np.array([_yaw_of(r) for r in rotations])
    deviation = np.column_stack((np.remainder(directions - direction + math.pi / 2, math.pi) - math.pi / 2,
                                 np.remainder(yaws - yaw + math.pi, 2 * math.pi) - math.pi))
    covariance = np.einsum("n,ni,nj->ij", weight, deviation, deviation)
    covariance[0, 0] += step ** 2 / 12
    covariance[1, 1] += float(weight @ yaw_variance) * variance
    return rotation, direction, covariance, inlier


def _profile(x1, x2, focal, start: np.ndarray, directions: np.ndarray, threshold: float, steps: int = 3):
    """At every direction: the rotation fitted by Gauss–Newton (from ``start``, on the matches
    within ``threshold``), the truncated cost Σ min(r², threshold²), the yaw's variance per
    unit of pixel variance, and the inlier mask."""
    H = len(directions)
    centres = _centres(directions)
    rotations = np.repeat(start[None], H, axis=0)
    h = 1e-7
    nudges = _rotations(np.eye(3) * h)   # small rotations about x, y, z
    for _ in range(steps):
        residual = _sampson(rotations, centres, x1, x2, focal)
        within = residual ** 2 < threshold ** 2
        J = np.stack([(_sampson(nudges[k] @ rotations, centres, x1, x2, focal) - residual) / h for k in range(3)],
                     axis=2) * within[..., None]      # (H, N, 3)
        information = J.transpose(0, 2, 1) @ J + 1e-9 * np.eye(3)
        delta = -np.linalg.solve(information, np.einsum("hnk,hn->hk", J, residual)[..., None])[..., 0]
        rotations = _rotations(delta) @ rotations
    residual = _sampson(rotations, centres, x1, x2, focal)
    within = residual ** 2 < threshold ** 2
    cost = np.where(within, residual ** 2, threshold ** 2).sum(axis=1)
    yaw_variance = np.linalg.inv(information)[:, 1, 1]    # the rotation vector's y component is the yaw
    return rotations, cost, yaw_variance, within


def _yaw_of(rotation: np.ndarray) -> float:
    """The yaw (counter-clockwise, radians) of the camera motion whose p_cur = R p_kf rotation is ``rotation``."""
    transform = np.eye(4)
    transform[:3, :3] = rotation
    return increment_from_transform(transform)[2]


def _yaw_only(x1: np.ndarray, x2: np.ndarray) -> float:
    """The yaw that best maps the keyframe's bearings onto the current ones by rotation alone
    (the median change of the bearings' angle about the up axis)."""
    angle1 = np.arctan2(x1[:, 0], x1[:, 2])
    angle2 = np.arctan2(x2[:, 0], x2[:, 2])
    # Turning left by α moves every bearing right by α.
    return float(np.median(np.remainder(angle2 - angle1 + math.pi, 2 * math.pi) - math.pi))


def _cheiral(x1: np.ndarray, x2: np.ndarray, rotation: np.ndarray, direction: float) -> float:
    """``direction`` or its opposite, whichever puts more points in front of both cameras."""
    t = -rotation @ _centres(np.array([direction]))[0]
    rotated = x1 @ rotation.T
    # λ2 x2 = λ1 R x1 + t, least squares for (λ1, λ2) per match.
    A = np.stack((rotated, -x2), axis=2)                  # (n, 3, 2)
    AtA = np.einsum("nki,nkj->nij", A, A)
    Atb = np.einsum("nki,k->ni", A, -t)
    det = AtA[:, 0, 0] * AtA[:, 1, 1] - AtA[:, 0, 1] ** 2
    det = np.where(det == 0, 1.0, det)
    depth1 = (AtA[:, 1, 1] * Atb[:, 0] - AtA[:, 0, 1] * Atb[:, 1]) / det
    depth2 = (AtA[:, 0, 0] * Atb[:, 1] - AtA[:, 0, 1] * Atb[:, 0]) / det
    in_front = int(((depth1 > 0) & (depth2 > 0)).sum())
    behind = int(((depth1 < 0) & (depth2 < 0)).sum())
    return direction if in_front >= behind else math.remainder(direction + math.pi, 2 * math.pi)


def _parallax(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, rotation: np.ndarray) -> float:
    """Median distance (pixels) between the current features and where the rotation alone puts
    the keyframe's: how much the translation shows in the images."""
    rotated = x1 @ rotation.T
    predicted = rotated[:, :2] / rotated[:, 2:3]
    return float(np.median(np.linalg.norm(predicted - x2[:, :2], axis=1)) * K[0, 0])
