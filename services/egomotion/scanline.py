"""RatSLAM's scanline intensity-profile odometry (monocular, no features).

Method as published (Milford & Wyeth, "Mapping a suburb with a single camera using a
biologically inspired SLAM system", IEEE T-RO 24(5), 2008, Sec. IV-A; Ball et al.,
"OpenRatSLAM", Autonomous Robots 34, 2013, Sec. 4.2), written from those descriptions:

1. Each crop region of the image is reduced to a scanline intensity profile: the mean
   intensity of each column, scaled to 0..1.
2. Rotation: consecutive profiles of the rotation region are compared at every relative
   shift s within ±max_shift_px by the mean absolute difference over their overlap; the
   shift with the smallest difference, times the degrees per pixel of the camera
   (field of view / image width), is the yaw of the frame.
3. Speed: the smallest mean absolute difference of the translation region's profiles (the
   residual that no shift explains, which grows with how fast the scene changes) times a
   per-dataset scaling factor is the speed in m/s, clipped to vtrans_max; divided by the
   camera rate it is the forward step of the frame.

The parameters keep OpenRatSLAM's names so its per-dataset values (St Lucia:
services/egomotion/presets/stlucia.toml) carry over unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.common.images import grey
from services.common.settings import setting
from services.egomotion.base import Increment, NoiseModel, noise_setting, zero_increment

@dataclass(frozen=True)
class ScanlineParams(NoiseModel):
    """Crop regions in pixels ([min, max) columns and rows; −1 as a maximum means the image
    edge), camera field of view and rate, speed scaling and clip, shift search range."""

    vtrans_image_x_min: int = setting(0, ge=0, help="translation crop: first column, px")
    vtrans_image_x_max: int = setting(-1, ge=-1, help="translation crop: column to stop before, px (-1: the image edge)")
    vtrans_image_y_min: int = setting(0, ge=0, help="translation crop: first row, px")
    vtrans_image_y_max: int = setting(-1, ge=-1, help="translation crop: row to stop before, px (-1: the image edge)")
    vrot_image_x_min: int = setting(0, ge=0, help="rotation crop: first column, px")
    vrot_image_x_max: int = setting(-1, ge=-1, help="rotation crop: column to stop before, px (-1: the image edge)")
    vrot_image_y_min: int = setting(0, ge=0, help="rotation crop: first row, px")
    vrot_image_y_max: int = setting(-1, ge=-1, help="rotation crop: row to stop before, px (-1: the image edge)")
    # width/fx makes one column 1/fx radians, the true angle of a column at the image centre; the
    # lens's real field of view, 2·atan(width/2fx), would make every rotation ~11% short on NuBot
    # (65.9° vs 74.2°).
    camera_fov_deg: float | None = setting(None, gt=0.0, le=360.0,
                                           help="horizontal field of view for degrees per column, deg; none: width/fx "
                                                "radians from the camera (one column = 1/fx rad), else 50 (OpenRatSLAM's)")
    camera_hz: float = setting(10.0, gt=0.0, help="camera rate, Hz: the speed in m/s is divided by it")
    vtrans_scaling: float = setting(100.0, ge=0.0, help="speed in m/s per unit of residual profile difference "
                                                        "(OpenRatSLAM's 100; calibrated per dataset)")
    vtrans_max: float = setting(20.0, ge=0.0, help="speed clip, m/s")
    max_shift_px: int = setting(40, ge=0, help="profile shifts searched each way, columns (OpenRatSLAM searches 40)")
    # Not in the papers; off reproduces their integer shifts.
    subpixel: bool = setting(False, help="refine the best shift to a fraction of a column by a parabola through the "
                                         "three lowest differences (not in the papers)")
    # A pinhole image stretches toward its edges: a 3° turn moves the centre 1/cos²(35°) = 1.5
    # times less than the edge of a 70° view. Not in the papers, off reproduces them.
    equiangular: bool = setting(False, help="resample each profile to equal steps of viewing angle (1/fx rad) before "
                                            "matching, so that a turn shifts every part equally (needs the camera; not "
                                            "in the papers)")

    # Uncertainty per frame (base.NoiseModel): intensity profiles measure speed and turn coarsely
    # (on the synthetic world, 30 mm forward at 0.1 m per frame and 13 mrad yaw rms).
    sigma_translation: float = noise_setting("sigma_translation", 0.4)
    sigma_translation_floor: float = noise_setting("sigma_translation_floor", 0.005)
    sigma_yaw: float = noise_setting("sigma_yaw", 0.1)
    sigma_yaw_per_m: float = noise_setting("sigma_yaw_per_m", 0.0)
    sigma_yaw_floor: float = noise_setting("sigma_yaw_floor", 0.02)


def intensity_profile(image: np.ndarray, x_min: int, x_max: int, y_min: int, y_max: int) -> np.ndarray:
    """Column-mean intensity (0..1) of the crop [y_min:y_max, x_min:x_max]; −1 maxima mean the
    image edge and the crop is clipped to the image."""
    height, width = image.shape[:2]
    x_max = width if x_max < 0 else min(x_max, width)
    y_max = height if y_max < 0 else min(y_max, height)
    x_min, y_min = max(0, min(x_min, x_max - 1)), max(0, min(y_min, y_max - 1))
    crop = image[y_min:y_max, x_min:x_max]
    return crop.mean(axis=0, dtype=np.float64) / 255.0


def _crop_start(x_min: int, width: int) -> int:
    return max(0, min(x_min, width - 1))


def equiangular_profile(profile: np.ndarray, first_column: int, fx: float, cx: float) -> np.ndarray:
    """``profile`` (columns first_column, first_column+1, ...) resampled at equal steps of
    viewing angle, 1/fx radians apart, by linear interpolation: column u sees the angle
    atan((u − cx)/fx) from the optical axis."""
    columns = first_column + np.arange(len(profile))
    angles = np.arctan((columns - cx) / fx)
    samples = np.arange(angles[0], angles[-1], 1.0 / fx)
    return np.interp(cx + fx * np.tan(samples), columns, profile)


@dataclass(frozen=True)
class ProfileMatch:
    """Best relative shift of two profiles: content at previous column k is at current column
    k + shift; cost is the mean absolute difference at that shift; overlap its column count."""

    shift: float
    cost: float
    overlap: int
    distinctness: float  # 1 − best/median cost: 0 for a featureless profile, near 1 for a sharp minimum


def match_profiles(current: np.ndarray, previous: np.ndarray, max_shift: int, subpixel: bool = False) -> ProfileMatch:
    """Search shifts in ±max_shift (limited to half the profile so the overlap stays large)."""
    n = min(len(current), len(previous))
    max_shift = int(min(max_shift, n // 2))
    shifts = np.arange(-max_shift, max_shift + 1)
    costs = np.empty(len(shifts))
    for i, s in enumerate(shifts):
        if s >= 0:
            costs[i] = np.abs(current[s:n] - previous[: n - s]).mean()
        else:
            costs[i] = np.abs(current[: n + s] - previous[-s:n]).mean()
    # Ties (a featureless profile) resolve to the smallest shift, i.e. no rotation.
    best = int(np.argmin(costs + 1e-12 * np.abs(shifts)))
    shift = float(shifts[best])
    if subpixel and 0 < best < len(costs) - 1:
        left, centre, right = costs[best - 1], costs[best], costs[best + 1]
        curvature = left - 2.0 * centre + right
        if curvature > 0:
            shift += float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))
    median = float(np.median(costs))
    distinctness = 0.0 if median <= 0 else float(np.clip(1.0 - costs[best] / median, 0.0, 1.0))
    return ProfileMatch(shift, float(costs[best]), int(n - abs(shifts[best])), distinctness)


class ScanlineEstimator:
    """RatSLAM intensity-profile odometry; state is the previous frame's two profiles."""

    name = "scanline"

    def __init__(self, params: ScanlineParams, camera: Any = None) -> None:
        self.params = params
        self.camera = camera
        self._previous: tuple[np.ndarray, np.ndarray] | None = None

    def field_of_view_deg(self, width: int) -> float:
        if self.params.camera_fov_deg is not None:
            return self.params.camera_fov_deg
        if self.camera is not None and self.camera.fx > 0:
            return math.degrees(width / self.camera.fx)
        return 50.0

    def estimate(self, frame: Any) -> Increment:
        image = grey(frame.left)
        if self.camera is None and getattr(frame, "camera", None) is not None:
            self.camera = frame.camera
        p = self.params
        vtrans = intensity_profile(image, p.vtrans_image_x_min, p.vtrans_image_x_max, p.vtrans_image_y_min, p.vtrans_image_y_max)
        vrot = intensity_profile(image, p.vrot_image_x_min, p.vrot_image_x_max, p.vrot_image_y_min, p.vrot_image_y_max)
        if p.equiangular and self.camera is not None and p.camera_fov_deg is None:
            vrot = equiangular_profile(vrot, _crop_start(p.vrot_image_x_min, image.shape[1]), self.camera.fx, self.camera.cx)
        previous, self._previous = self._previous, (vtrans, vrot)
        if previous is None or previous[0].shape != vtrans.shape or previous[1].shape != vrot.shape:
            return zero_increment()
        rotation = match_profiles(vrot, previous[1], p.max_shift_px, p.subpixel)
        translation = match_profiles(vtrans, previous[0], p.max_shift_px, p.subpixel)
        # Content moving right in the image (positive shift) means the camera turned left:
        # counter-clockwise, positive yaw. Degrees per pixel use the whole image width.
        yaw = math.radians(rotation.shift * self.field_of_view_deg(image.shape[1]) / image.shape[1])
        speed = min(translation.cost * p.vtrans_scaling, p.vtrans_max)
        return Increment(
            forward=speed / p.camera_hz,
            left=0.0,
            yaw=yaw,
            transform=None,
            quality=rotation.distinctness,
            inliers=rotation.overlap,
            match_cost=translation.cost,
            scaled=True,
        )
