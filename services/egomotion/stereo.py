"""Feature-based stereo visual odometry in the spirit of LIBVISO2 (Geiger, Ziegler & Stiller,
"StereoScan: Dense 3d reconstruction in real-time", IEEE IV 2011), built from OpenCV parts.

Per frame:
1. Features in the left image, bucketed so they spread over the image (StereoScan III-A): the
   last frame's inlier tracks, at most features_per_bucket a bucket (carry_tracks), topped up
   with the strongest new FAST corners (all new when carry_tracks is off, as LIBVISO2 does).
2. Each feature matched into the right image by pyramidal Lucas–Kanade with a forward–backward
   check; on rectified images a match must lie on the same row (|Δv| ≤ max_row_error_px) with a
   positive disparity d (StereoScan's epipolar constraint). A carried feature's search starts
   at the disparity its 3D point predicts after the motion just found, so a shallow pyramid
   (carried_stereo_pyramid_levels) reaches it; a new one starts at the median of those
   predictions in its bucket (else the last frame's median disparity), with the full pyramid.
3. Triangulated: Z = f·b/d, X = (u − cu)·Z/f, Y = (v − cv)·Z/f.
4. Next frame: those points are tracked from the previous left image into the new one (LK
   seeded with the position the last motion predicts), and the camera transform comes from
   PnP with RANSAC on the 3D–2D matches, refined by Levenberg–Marquardt on the inliers
   (StereoScan III-B minimises the same reprojection error with Gauss–Newton inside RANSAC).

A frame with too few tracks or inliers (blank, blurred, covered lens) gives a zero-quality
increment (zero motion, or the last motion if failure_motion = "hold") and never raises.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from services.common.features import (
    FeatureParams,
    TrackParams,
    bucket_of,
    detect_bucketed,
    first_per_bucket,
    global_shift,
    track,
)
from services.common.geometry import invert_transform, transform_from_rt
from services.common.images import grey
from services.egomotion.base import (
    EgomotionError,
    Increment,
    NoiseModel,
    failure_motion_setting,
    increment_with_transform,
    zero_increment,
)
from services.common.settings import setting

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class StereoParams(NoiseModel):
    fast_threshold: int = setting(20, ge=1, le=255, help="FAST corner threshold, grey levels (lowered to a quarter "
                                                          "once if there are fewer corners than buckets)")
    bucket_size_px: int = setting(50, ge=1, help="bucketing: side of a bucket, px")
    features_per_bucket: int = setting(4, ge=1, help="bucketing: corners kept per bucket")
    klt_window_px: int = setting(11, ge=3, help="Lucas–Kanade window, px")
    # Disparities of close objects reach ~100 px (NuBot: f·b = 59 px·m, so 0.6 m away is 99 px).
    stereo_pyramid_levels: int = setting(4, ge=0, help="pyramid depth for left–right matching of new corners "
                                                       "(disparities up to ~100 px)")
    track_pyramid_levels: int = setting(3, ge=0, help="pyramid depth for frame-to-frame tracking")
    forward_backward_px: float = setting(1.0, ge=0.0, help="forward–backward check of frame-to-frame tracks, px (0: off)")
    # features.refine_affine_brightness: under a lens vignette, plain Lucas–Kanade makes forward
    # motion 0.5 % short on the synthetic world.
    affine_brightness: bool = setting(True, help="refine frame-to-frame tracks letting each window's brightness change "
                                                 "by a gain and an offset (false: plain Lucas–Kanade)")
    stereo_forward_backward_px: float = setting(1.0, ge=0.0, help="forward–backward check of the left–right matches, "
                                                                  "px (0: off, the row check alone)")
    max_row_error_px: float = setting(1.0, ge=0.0, help="epipolar check on rectified images: largest row difference "
                                                        "of a left–right match, px")
    min_disparity_px: float = setting(0.5, ge=0.0, help="smallest disparity of a triangulated point, px")
    ransac_reprojection_px: float = setting(2.0, gt=0.0, help="RANSAC inlier threshold, px of reprojection error "
                                                              "(LIBVISO2's)")
    ransac_iterations: int = setting(200, ge=1, help="RANSAC iterations (LIBVISO2's)")
    min_inliers: int = setting(12, ge=4, help="fewer inliers is a failed frame (PnP needs 4 points)")
    retry_below_quality: float = setting(0.3, ge=0.0, le=1.0, help="below this quality the tracking is retried seeded "
                                                                   "by the global image shift (phase correlation)")
    quality_inliers: int = setting(80, ge=1, help="inliers at which quality saturates (quality = inlier ratio × "
                                                  "min(1, inliers / this))")
    predict: bool = setting(True, help="seed frame-to-frame tracking with the last motion (constant velocity)")
    # Steps 1–2 of the module docstring.
    carry_tracks: bool = setting(True, help="keep the last frame's inlier tracks as this frame's features, matched "
                                            "into the right image from their predicted disparity (false: detect "
                                            "afresh every frame, LIBVISO2's way)")
    carried_stereo_pyramid_levels: int = setting(1, ge=0, help="pyramid depth for left–right matching of carried "
                                                               "features (searched from their predicted disparity)")
    failure_motion: str = failure_motion_setting()

    # Uncertainty per frame (base.NoiseModel): the synthetic world's per-frame errors at 0.1 m per
    # frame are 0.9 mm forward, 1.2 mm left, 0.4 mrad yaw rms (1.3, 1.6, 0.5 with plain Lucas–Kanade);
    # these defaults are about twice the latter.

    def features(self) -> FeatureParams:
        return FeatureParams(self.fast_threshold, self.bucket_size_px, self.features_per_bucket)


@dataclass
class _StereoKeyframe:
    """The last frame whose features could be triangulated: its left image, its features and
    their 3D points (its camera frame), and the transform from its camera to the camera of
    the most recent frame (identity unless later frames failed to triangulate)."""

    left: np.ndarray
    points: np.ndarray  # (N, 2) float32 pixel positions in the left image
    landmarks: np.ndarray  # (N, 3) metres, camera frame
    disparity_median: float = 0.0
    to_last: np.ndarray = field(default_factory=lambda: np.eye(4))


class StereoEstimator:
    """LIBVISO2-like stereo odometry; state is the previous frame's triangulated features."""

    name = "stereo"

    def __init__(self, params: StereoParams, camera: Any) -> None:
        self.params = params
        self.camera = camera
        self._keyframe: _StereoKeyframe | None = None
        self._last = zero_increment()
        self._stereo_track = TrackParams(params.klt_window_px, params.stereo_pyramid_levels, params.stereo_forward_backward_px)
        self._carried_track = TrackParams(params.klt_window_px, params.carried_stereo_pyramid_levels, params.stereo_forward_backward_px)
        self._frame_track = TrackParams(params.klt_window_px, params.track_pyramid_levels, params.forward_backward_px, params.affine_brightness)

    def estimate(self, frame: Any) -> Increment:
        camera = getattr(frame, "camera", None) or self.camera
        if frame.right is None:
            raise EgomotionError(f"stereo estimator: frame {frame.seq} has no right image (the source is monocular)")
        if camera is None or camera.baseline <= 0:
            raise EgomotionError("stereo estimator: the camera has no stereo baseline (give a calibration)")
        left, right = grey(frame.left), grey(frame.right)
        if left.shape != right.shape:
            raise EgomotionError(f"stereo estimator: frame {frame.seq} left {left.shape} and right {right.shape} differ in size")
        K = camera.matrix()

        increment = zero_increment()
        to_current = None
        tracks = None
        keyframe = self._keyframe
        if keyframe is not None and keyframe.left.shape == left.shape:
            increment, tracks = self._motion(keyframe, left, K)
            if increment.quality > 0.0:
                # Motion since the keyframe; the frame's own increment removes what the
                # frames between keyframe and now already reported.
                to_current = increment.transform
                increment = increment_with_transform(
                    to_current @ invert_transform(keyframe.to_last),
                    quality=increment.quality,
                    inliers=increment.inliers,
                    match_cost=increment.match_cost,
                )
            elif self.params.failure_motion == "hold":
                last = self._last
                increment = Increment(last.forward, last.left, last.yaw, last.transform, 0.0, increment.inliers, increment.match_cost)
        if increment.quality > 0.0:
            self._last = increment
        carried = None
        if to_current is not None and tracks is not None and self.params.carry_tracks:
            # The inliers' 3D points moved into this camera predict their disparity f·b/Z.
            positions, points = tracks
            depth = points @ to_current[2, :3] + to_current[2, 3]
            ahead = depth > 0
            carried = (positions[ahead], camera.fx * camera.baseline / depth[ahead])
        fresh = self._triangulate(left, right, camera, carried)
        if len(fresh.points) >= self.params.min_inliers or to_current is None or keyframe is None:
            self._keyframe = fresh
        else:
            # This frame's stereo failed (e.g. NuBot frame 152: the left image repeats frame 151
            # while the right one is new) but its pose is known: keep tracking the older keyframe.
            keyframe.to_last = to_current
        return increment

    # -- stereo matching and triangulation (steps 1–3)

    def _triangulate(
        self, left: np.ndarray, right: np.ndarray, camera: Any, carried: tuple[np.ndarray, np.ndarray] | None
    ) -> _StereoKeyframe:
        """Features of ``left`` matched into ``right`` and triangulated. ``carried`` are the
        features tracked from the last keyframe with the disparities their 3D points predict
        here: they are kept (at most features_per_bucket a bucket) and only the buckets' rest
        is detected afresh."""
        p = self.params
        columns = left.shape[1] // p.bucket_size_px + 1
        held, seeds = (np.empty((0, 2), np.float32), np.empty(0)) if carried is None else carried
        keep = np.sort(first_per_bucket(bucket_of(held, p.bucket_size_px, columns), p.features_per_bucket))
        held, seeds = held[keep], seeds[keep]
        new = detect_bucketed(left, p.features(), held=held)
        # New features are searched from the median disparity the carried ones predict in
        # their bucket, else from the median disparity of the last frame.
        new_seeds = np.full(len(new), self._keyframe.disparity_median if self._keyframe is not None else 0.0)
        if len(held) and len(new):
            medians = _bucket_medians(bucket_of(held, p.bucket_size_px, columns), seeds, bucket_of(new, p.bucket_size_px, columns))
            known = np.isfinite(medians)
            new_seeds[known] = medians[known]
        points = np.concatenate((held, new)).astype(np.float32)
        if len(points) == 0:
            return _StereoKeyframe(left, points, np.empty((0, 3)))
        guess = points.copy()
        guess[:, 0] -= np.concatenate((seeds, new_seeds))
        matched = np.empty_like(points)
        good = np.zeros(len(points), bool)
        for part, tracking in ((slice(0, len(held)), self._carried_track), (slice(len(held), None), self._stereo_track)):
            if len(points[part]):
                matched[part], good[part] = track(left, right, points[part], tracking, guess[part])
        disparity = points[:, 0] - matched[:, 0]
        good &= (np.abs(points[:, 1] - matched[:, 1]) <= p.max_row_error_px) & (disparity >= p.min_disparity_px)
        points, disparity = points[good], disparity[good].astype(np.float64)
        depth = camera.fx * camera.baseline / disparity
        landmarks = np.column_stack(
            (
                (points[:, 0] - camera.cx) * depth / camera.fx,
                (points[:, 1] - camera.cy) * depth / camera.fy,
                depth,
            )
        )
        median = float(np.median(disparity)) if len(disparity) else 0.0
        return _StereoKeyframe(left, points, landmarks, median)

    # -- temporal tracking and pose (step 4)

    def _motion(
        self, keyframe: _StereoKeyframe, left: np.ndarray, K: np.ndarray
    ) -> tuple[Increment, tuple[np.ndarray, np.ndarray] | None]:
        """Track the keyframe's features into ``left`` and solve the pose. The first try seeds
        tracking with the last motion; if that fails, a second try seeds it with the global
        image shift found by phase correlation, which catches sudden turns the pyramid cannot
        reach (NuBot frame 153: a 23° turn after a dropped frame slides the image ~194 px).
        Also returns the inliers' positions in ``left`` and their 3D points in the keyframe's
        camera (None when no pose was found)."""
        p = self.params
        if len(keyframe.points) < p.min_inliers:
            return zero_increment(inliers=len(keyframe.points)), None
        guess = None
        if p.predict and self._last.transform is not None:
            guess = _project(keyframe.landmarks, self._last.transform @ keyframe.to_last, K)
        result = self._pose(keyframe, left, K, guess)
        if result[0].quality < p.retry_below_quality:
            dx, dy = global_shift(keyframe.left, left)
            retry = self._pose(keyframe, left, K, keyframe.points + np.float32([dx, dy]))
            if retry[0].quality > result[0].quality:
                result = retry
        return result

    def _pose(
        self, keyframe: _StereoKeyframe, left: np.ndarray, K: np.ndarray, guess: np.ndarray | None
    ) -> tuple[Increment, tuple[np.ndarray, np.ndarray] | None]:
        p = self.params
        tracked, good = track(keyframe.left, left, keyframe.points, self._frame_track, guess)
        if good.sum() < p.min_inliers:
            return zero_increment(inliers=int(good.sum())), None
        objects = keyframe.landmarks[good]
        images = tracked[good].astype(np.float64)
        try:
            found, rvec, tvec, inliers = cv2.solvePnPRansac(
                objects,
                images,
                K,
                None,
                iterationsCount=p.ransac_iterations,
                reprojectionError=p.ransac_reprojection_px,
                confidence=0.999,
                flags=cv2.SOLVEPNP_EPNP,
            )
        except cv2.error as error:
            logger.debug("stereo: PnP failed: %s", error)
            return zero_increment(), None
        if not found or inliers is None or len(inliers) < p.min_inliers:
            return zero_increment(inliers=0 if inliers is None else len(inliers)), None
        inliers = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(objects[inliers], images[inliers], K, None, rvec, tvec)
        projected, _ = cv2.projectPoints(objects[inliers], rvec, tvec, K, None)
        residual = projected.reshape(-1, 2) - images[inliers]
        rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
        quality = len(inliers) / len(objects) * min(1.0, len(inliers) / p.quality_inliers)
        transform = transform_from_rt(rvec, tvec)
        increment = increment_with_transform(transform, quality=quality, inliers=len(inliers), match_cost=rms)
        return increment, (images[inliers].astype(np.float32), objects[inliers])


def _bucket_medians(buckets: np.ndarray, values: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """The median of ``values`` in each bucket of ``wanted`` (NaN where a bucket has none)."""
    order = np.lexsort((values, buckets))
    buckets, values = buckets[order], values[order]
    starts = np.flatnonzero(np.r_[True, buckets[1:] != buckets[:-1]])
    counts = np.diff(np.r_[starts, len(buckets)])
    middle = starts + (counts - 1) // 2
    position = np.searchsorted(buckets[starts], wanted)
    position = np.minimum(position, len(starts) - 1)
    found = buckets[starts][position] == wanted
    return np.where(found, (values[middle] + values[starts + counts // 2])[position] / 2, np.nan)


def _project(points: np.ndarray, transform: np.ndarray, K: np.ndarray) -> np.ndarray:
    moved = points @ transform[:3, :3].T + transform[:3, 3]
    z = np.maximum(moved[:, 2:3], 1e-6)
    return (moved[:, :2] / z) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
