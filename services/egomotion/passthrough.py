"""Ego-motion taken from the frame itself: its odometry (wheel encoders, a motion-only CSV) or
the increment between consecutive ground-truth poses, with optional Gaussian noise.

For motion-only data, and for controlled experiments: exact inputs to the grid-cell network,
or inputs with known, seeded noise of given standard deviations per frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from services.common.geometry import invert_transform, transform_from_increment
from services.egomotion.base import (
    EgomotionError,
    Increment,
    NoiseModel,
    increment_with_transform,
    noise_setting,
    zero_increment,
)
from services.common.settings import setting

SOURCES = ("auto", "odometry", "ground_truth")


@dataclass(frozen=True)
class PassthroughParams(NoiseModel):
    source: str = setting("auto", choices=SOURCES, help="where increments come from: auto (odometry when the frame "
                                                        "has it, else ground truth), odometry, ground_truth")
    noise_forward: float = setting(0.0, ge=0.0, help="standard deviation of Gaussian noise added to forward per frame, m")
    noise_left: float = setting(0.0, ge=0.0, help="standard deviation of Gaussian noise added to left per frame, m")
    noise_yaw: float = setting(0.0, ge=0.0, help="standard deviation of Gaussian noise added to yaw per frame, rad")
    seed: int = setting(0, ge=0, help="noise seed: a frame's noise is drawn from (seed, seq), the same whoever "
                                      "estimates it")

    # Uncertainty per frame (base.NoiseModel), to which the added noise's variances are added.
    sigma_translation: float = noise_setting("sigma_translation", 0.01)
    sigma_translation_floor: float = noise_setting("sigma_translation_floor", 0.0005)
    sigma_yaw: float = noise_setting("sigma_yaw", 0.01)
    sigma_yaw_per_m: float = noise_setting("sigma_yaw_per_m", 0.002)
    sigma_yaw_floor: float = noise_setting("sigma_yaw_floor", 0.0002)

    def covariance(self, increment: Increment) -> np.ndarray | None:
        covariance = super().covariance(increment)
        if covariance is not None:
            covariance = covariance + np.diag([self.noise_forward ** 2, self.noise_left ** 2, self.noise_yaw ** 2])
        return covariance


class PassthroughEstimator:
    """Increments from the frame's odometry or ground truth, plus seeded noise."""

    name = "passthrough"

    def __init__(self, params: PassthroughParams, camera: Any = None) -> None:
        self.params = params
        self._previous_pose: np.ndarray | None = None
        self._first = True

    def estimate(self, frame: Any) -> Increment:
        exact = self._exact(frame)
        first, self._first = self._first, False
        if first:
            return zero_increment()
        if not self._noisy():
            return exact
        # Drawn from (seed, frame): a frame's noise is the same whichever estimator, restarted or
        # one of several instances (docs/pipeline.md, sharded ego-motion), draws it.
        rng = np.random.default_rng([self.params.seed, int(frame.seq)])
        noise = rng.normal(0.0, [self.params.noise_forward, self.params.noise_left, self.params.noise_yaw])
        forward, left, yaw = exact.forward + noise[0], exact.left + noise[1], exact.yaw + noise[2]
        return Increment(forward, left, yaw, transform_from_increment(forward, left, yaw), 1.0, 1, 0.0)

    def _noisy(self) -> bool:
        p = self.params
        return p.noise_forward > 0 or p.noise_left > 0 or p.noise_yaw > 0

    def _exact(self, frame: Any) -> Increment:
        odometry = getattr(frame, "odometry", None)
        pose = getattr(frame, "ground_truth", None)
        use_odometry = self.params.source == "odometry" or (self.params.source == "auto" and odometry is not None)
        if use_odometry:
            if odometry is None:
                raise EgomotionError(f"passthrough estimator: frame {frame.seq} has no odometry (source = odometry)")
            forward, left, yaw = (float(v) for v in odometry)
            return Increment(forward, left, yaw, transform_from_increment(forward, left, yaw), 1.0, 1, 0.0)
        if pose is None:
            raise EgomotionError(f"passthrough estimator: frame {frame.seq} has neither odometry nor ground truth")
        pose = np.asarray(pose, dtype=float)
        previous, self._previous_pose = self._previous_pose, pose
        if previous is None:
            return zero_increment()
        # p_cur = inv(pose_cur) · pose_prev · p_prev: the camera transform between the frames.
        return increment_with_transform(invert_transform(pose) @ previous, quality=1.0, inliers=1, match_cost=0.0)
