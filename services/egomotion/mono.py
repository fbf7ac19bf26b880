"""Monocular feature odometry: tracked corners, the essential matrix, and a metric scale from
outside the images.

Per frame (Nistér, "An efficient solution to the five-point relative pose problem", PAMI 2004;
Scaramuzza & Fraundorfer, "Visual Odometry, Part I", IEEE RAM 2011, Sec. "2-D-to-2-D"):
1. Bucketed FAST corners of the previous frame tracked into this one (pyramidal Lucas–Kanade,
   forward–backward check; retried seeded by the global image shift after a failure).
2. Model selection between a pure rotation and a general motion: the rotation that best maps
   the previous bearings onto the current ones (Kabsch/Wahba, least squares) is fitted first;
   if it explains the tracks to within min_parallax_px (median), the motion has no measurable
   translation (the essential matrix is degenerate then) and translation is zero, or along the
   optical axis when the frame's odometry says the robot moved.
3. Otherwise the essential matrix by the five-point algorithm inside MAGSAC++ with local
   optimisation (cv2.findEssentialMat, USAC_MAGSAC) and its decomposition with the
   cheirality check (cv2.recoverPose) give the rotation and the direction of translation.
4. Scale, in this order (scale_source = "auto"): the speed of the frame's odometry; else the
   known height of the camera above a ground plane, fitted by RANSAC to the triangulated
   points below the horizon (Kitt et al., "Monocular visual odometry using a planar road
   model to solve scale ambiguity", ECMR 2011), as the running median over the last
   scale_window frames; else none: the translation has unit length per frame and the
   increment is flagged ``scaled=False``. A frame whose ground plane cannot be found reuses
   the running median, with its quality halved.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from services.common.images import grey
from services.common.settings import setting
from services.egomotion.base import (Increment, NoiseModel, failure_motion_setting, increment_with_transform,
                                      noise_setting, zero_increment)
from services.common.features import FeatureParams, TrackParams, detect_bucketed, global_shift, track

logger = logging.getLogger(__name__)

SCALE_SOURCES = ("auto", "odometry", "ground", "none")


@dataclass(frozen=True)
class MonoParams(NoiseModel):
    fast_threshold: int = setting(20, ge=1, le=255, help="FAST corner threshold, grey levels, as stereo")
    bucket_size_px: int = setting(50, ge=1, help="bucketing: side of a bucket, px")
    features_per_bucket: int = setting(4, ge=1, help="bucketing: corners kept per bucket")
    klt_window_px: int = setting(15, ge=3, help="Lucas–Kanade window, px")
    pyramid_levels: int = setting(3, ge=0, help="pyramid depth for frame-to-frame tracking")
    forward_backward_px: float = setting(1.0, ge=0.0, help="forward–backward check of the tracks, px (0: off)")
    ransac_threshold_px: float = setting(1.0, gt=0.0, help="essential-matrix RANSAC inlier threshold, px")
    min_inliers: int = setting(15, ge=5, help="fewer inliers is a failed frame (the essential matrix needs 5 points)")
    min_parallax_px: float = setting(0.7, ge=0.0, help="median residual of the pure-rotation model below which a "
                                                       "frame has no measurable translation, px")
    quality_inliers: int = setting(80, ge=1, help="inliers at which quality saturates")
    scale_source: str = setting("auto", choices=SCALE_SOURCES,
                                help="where metric scale comes from: auto (odometry, else ground plane, else none), "
                                     "odometry, ground, none")
    camera_height_m: float = setting(0.0, ge=0.0, help="height of the optical centre above the ground, m (KITTI: "
                                                       "1.65); 0: unknown")
    ground_margin_px: float = setting(40.0, ge=0.0, help="ground points are those imaged at least this many px below "
                                                         "the principal point")
    ground_max_tilt_deg: float = setting(5.0, ge=0.0, le=90.0, help="largest angle between the fitted ground normal "
                                                                    "and the camera's down axis, deg")
    ground_inlier_fraction: float = setting(0.05, gt=0.0, help="ground-plane inlier distance as a fraction of the "
                                                               "plane's distance from the camera")
    ground_min_points: int = setting(12, ge=3, help="fewest ground points for a plane fit (a plane needs 3)")
    # Single frames see few road points and scatter by ±25% on KITTI; a vehicle's speed changes slowly.
    scale_window: int = setting(9, ge=1, help="frames in the running median of the ground scale")
    failure_motion: str = failure_motion_setting()

    # Uncertainty per frame (base.NoiseModel): the scale comes from outside the images.
    sigma_translation: float = noise_setting("sigma_translation", 0.1)
    sigma_translation_floor: float = noise_setting("sigma_translation_floor", 0.002)
    sigma_yaw: float = noise_setting("sigma_yaw", 0.03)
    sigma_yaw_per_m: float = noise_setting("sigma_yaw_per_m", 0.01)
    sigma_yaw_floor: float = noise_setting("sigma_yaw_floor", 0.003)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.scale_source == "ground" and self.camera_height_m <= 0:
            raise ValueError("scale_source 'ground' needs camera_height_m > 0")


class MonoEstimator:
    """Monocular feature odometry; state is the previous image and its corners."""

    name = "mono"
    # Frames per block when the egomotion service runs it in blocks (services/egomotion/shards.py):
    # a block start restarts the median of recent ground scales (scale_window), so mono's blocks
    # are longer than the default 4 (docs/pipeline.md: per-frame error on the KITTI clip).
    shard_block = 16

    def __init__(self, params: MonoParams, camera: Any) -> None:
        self.params = params
        self.camera = camera
        self._previous: tuple[np.ndarray, np.ndarray] | None = None
        self._last = zero_increment()
        self._scales: list[float] = []  # recent per-frame ground scales, newest last
        self._features = FeatureParams(params.fast_threshold, params.bucket_size_px, params.features_per_bucket)
        self._tracking = TrackParams(params.klt_window_px, params.pyramid_levels, params.forward_backward_px)

    def estimate(self, frame: Any) -> Increment:
        camera = getattr(frame, "camera", None) or self.camera
        image = grey(frame.left)
        increment = zero_increment(scaled=self._scaled_possible(frame))
        if self._previous is not None and self._previous[0].shape == image.shape and camera is not None:
            increment = self._motion(self._previous, image, camera.matrix(), frame)
            if increment.quality == 0.0 and self.params.failure_motion == "hold":
                last = self._last
                increment = Increment(last.forward, last.left, last.yaw, last.transform, 0.0, increment.inliers, increment.match_cost, last.scaled)
        if increment.quality > 0.0:
            self._last = increment
        self._previous = (image, detect_bucketed(image, self._features))
        return increment

    def _scaled_possible(self, frame: Any) -> bool:
        source = self.params.scale_source
        if source == "none":
            return False
        if source == "odometry":
            return True
        return getattr(frame, "odometry", None) is not None or self.params.camera_height_m > 0

    def _motion(self, previous: tuple[np.ndarray, np.ndarray], image: np.ndarray, K: np.ndarray, frame: Any) -> Increment:
        previous_image, corners = previous
        p = self.params
        tracked, good = track(previous_image, image, corners, self._tracking)
        if good.sum() < p.min_inliers:
            dx, dy = global_shift(previous_image, image)
            tracked, good = track(previous_image, image, corners, self._tracking, corners + np.float32([dx, dy]))
        if good.sum() < p.min_inliers:
            return zero_increment(inliers=int(good.sum()), scaled=self._scaled_possible(frame))
        first, second = corners[good].astype(np.float64), tracked[good].astype(np.float64)

        rotation, rotation_residual, rotation_inliers = _rotation_only(first, second, K, 3.0 * p.ransac_threshold_px)
        if rotation_residual < p.min_parallax_px:
            direction = np.zeros(3)
            inliers, cost = rotation_inliers, rotation_residual
            ground_points = None
        else:
            try:
                # MAGSAC++ with local optimisation (OpenCV's USAC): a refined model, not the best
                # five-point sample; plain RANSAC leaves ~10° of error in the direction of a
                # short forward step on a 320×240 image.
                E, mask = cv2.findEssentialMat(first, second, K, method=cv2.USAC_MAGSAC, prob=0.999, threshold=p.ransac_threshold_px)
            except cv2.error as error:
                logger.debug("mono: essential matrix failed: %s", error)
                E, mask = None, None
            if E is None or E.shape != (3, 3) or mask is None or int(mask.sum()) < p.min_inliers:
                return zero_increment(inliers=0 if mask is None else int(mask.sum()), scaled=self._scaled_possible(frame))
            _, rotation, direction, _ = cv2.recoverPose(E, first, second, K, mask=mask.copy())
            inlier_mask = mask.ravel() > 0
            inliers = int(inlier_mask.sum())
            direction = direction.ravel() / max(np.linalg.norm(direction), 1e-12)
            cost = _sampson_rms(E, first[inlier_mask], second[inlier_mask], K)
            ground_points = (first[inlier_mask], second[inlier_mask])

        quality = inliers / len(first) * min(1.0, inliers / p.quality_inliers)
        scale, scaled, quality = self._scale(frame, rotation, direction, ground_points, K, quality)
        if not np.any(direction) and scaled and scale > 0:
            # No parallax but the robot moved (odometry): along the optical axis, the usual
            # forward motion of a vehicle whose scene is too distant to show it.
            direction = -rotation @ np.array([0.0, 0.0, 1.0])
        transform = np.eye(4)
        transform[:3, :3] = rotation
        transform[:3, 3] = direction * scale
        return increment_with_transform(transform, quality=quality, inliers=inliers, match_cost=cost, scaled=scaled)

    def _scale(
        self,
        frame: Any,
        rotation: np.ndarray,
        direction: np.ndarray,
        ground_points: tuple[np.ndarray, np.ndarray] | None,
        K: np.ndarray,
        quality: float,
    ) -> tuple[float, bool, float]:
        """(metres per unit of translation, whether that is metric, quality)."""
        p = self.params
        odometry = getattr(frame, "odometry", None)
        if p.scale_source in ("auto", "odometry") and odometry is not None:
            return math.hypot(odometry[0], odometry[1]), True, quality
        if p.scale_source == "odometry":
            return 0.0, True, 0.0  # promised odometry is missing: no usable motion
        if p.scale_source in ("auto", "ground") and p.camera_height_m > 0:
            if ground_points is None:  # pure rotation: nothing to scale
                return 0.0, True, quality
            height = ground_height(*ground_points, rotation, direction, K, p)
            if height is not None:
                self._scales = (self._scales + [p.camera_height_m / height])[-max(1, p.scale_window) :]
                return float(np.median(self._scales)), True, quality
            if self._scales:
                return float(np.median(self._scales)), True, 0.5 * quality
            return 0.0, True, 0.0
        return (0.0 if not np.any(direction) else 1.0), False, quality


def _rotation_only(first: np.ndarray, second: np.ndarray, K: np.ndarray, outlier_px: float) -> tuple[np.ndarray, float, int]:
    """Best pure rotation mapping the bearings of ``first`` onto those of ``second``
    (orthogonal Procrustes / Kabsch, refitted once without outliers), its median residual in
    pixels and its inlier count."""
    K_inv = np.linalg.inv(K)
    bearings = [_unit(np.column_stack((points, np.ones(len(points)))) @ K_inv.T) for points in (first, second)]
    keep = np.ones(len(first), bool)
    rotation = np.eye(3)
    residual = np.full(len(first), np.inf)
    for _ in range(2):
        if keep.sum() < 3:
            break
        # Kabsch: R maximising sum second_i · (R first_i).
        u, _, vt = np.linalg.svd(bearings[1][keep].T @ bearings[0][keep])
        d = np.sign(np.linalg.det(u @ vt))
        rotation = u @ np.diag([1.0, 1.0, d]) @ vt
        predicted = bearings[0] @ rotation.T @ K.T
        predicted = predicted[:, :2] / np.maximum(predicted[:, 2:3], 1e-9)
        residual = np.linalg.norm(predicted - second, axis=1)
        keep = residual < max(outlier_px, 3.0 * float(np.median(residual)))
    return rotation, float(np.median(residual)), int((residual < outlier_px).sum())


def _unit(vectors: np.ndarray) -> np.ndarray:
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def _sampson_rms(E: np.ndarray, first: np.ndarray, second: np.ndarray, K: np.ndarray) -> float:
    """RMS Sampson distance (pixels) of the matches to the epipolar geometry."""
    K_inv = np.linalg.inv(K)
    F = K_inv.T @ E @ K_inv
    x1 = np.column_stack((first, np.ones(len(first))))
    x2 = np.column_stack((second, np.ones(len(second))))
    Fx1, Ftx2 = x1 @ F.T, x2 @ F
    numerator = np.sum(x2 * Fx1, axis=1) ** 2
    denominator = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return float(np.sqrt(np.mean(numerator / np.maximum(denominator, 1e-12))))


def ground_height(
    first: np.ndarray, second: np.ndarray, rotation: np.ndarray, direction: np.ndarray, K: np.ndarray, p: MonoParams
) -> float | None:
    """Distance from the first camera to the ground plane in units of the (unit-length)
    translation, or None when no plane near-perpendicular to the camera's down axis is
    supported by enough points below the horizon."""
    below = first[:, 1] > K[1, 2] + p.ground_margin_px
    if below.sum() < p.ground_min_points:
        return None
    P1 = K @ np.hstack((np.eye(3), np.zeros((3, 1))))
    P2 = K @ np.hstack((rotation, direction.reshape(3, 1)))
    homogeneous = cv2.triangulatePoints(P1, P2, first[below].T, second[below].T)
    points = (homogeneous[:3] / homogeneous[3]).T
    points = points[(points[:, 2] > 0) & (points[:, 1] > 0) & np.all(np.isfinite(points), axis=1)]
    if len(points) < p.ground_min_points:
        return None
    # RANSAC over 3-point planes n·X = h with n close to the down axis (0, 1, 0); a fixed seed
    # keeps runs repeatable.
    rng = np.random.default_rng(0)
    cos_tilt = math.cos(math.radians(p.ground_max_tilt_deg))
    best_count, best_height, best_members = 0, None, None
    for _ in range(100):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        normal = np.cross(b - a, c - a)
        length = np.linalg.norm(normal)
        if length < 1e-12:
            continue
        normal /= length
        if normal[1] < 0:
            normal = -normal
        if normal[1] < cos_tilt:
            continue
        height = float(normal @ a)
        if height <= 0:
            continue
        members = np.abs(points @ normal - height) < p.ground_inlier_fraction * height
        if members.sum() > best_count:
            best_count, best_height, best_members = int(members.sum()), height, members
    if best_height is None or best_count < p.ground_min_points:
        return None
    # Least-squares refit on the members (plane through their centroid).
    members = points[best_members]
    centroid = members.mean(axis=0)
    normal = np.linalg.svd(members - centroid)[2][2]
    if normal[1] < 0:
        normal = -normal
    return float(normal @ centroid) if normal[1] >= cos_tilt and normal @ centroid > 0 else best_height
