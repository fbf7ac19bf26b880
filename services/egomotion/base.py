"""What every ego-motion estimator shares: the per-frame `Increment`, the `Estimator` protocol,
an increment from a camera transform (the transforms themselves: services/common/geometry.py),
and the parameter handling (plain dataclasses built from dicts, unknown keys rejected by name).

Conventions (DESIGN.md, docs/egomotion.md):
- Camera frame: x right, y down, z forward (KITTI, LIBVISO2, OpenCV).
- Body frame of an increment: x forward, y left, yaw counter-clockwise seen from above (z up).
- `Increment.transform` maps a point's coordinates in the previous camera frame to its
  coordinates in the current camera frame, p_cur = T p_prev. This is LIBVISO2's `Tr`
  (as in ../shared/data/nubot_scene1/libviso2_egomotion.csv) and what cv2.solvePnP and
  cv2.recoverPose return. The camera's own motion (its pose in the previous frame) is inv(T).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np

from services.common.errors import ConfigError, GridslamError
from services.common.geometry import increment_from_transform
from services.common.settings import check, setting


class EgomotionError(GridslamError):
    """An estimator cannot run on the input it was given (e.g. stereo without a right image)."""


class EstimatorConfigError(ConfigError):
    """Unknown estimator, unknown or invalid parameter, missing calibration."""


@dataclass(frozen=True)
class Increment:
    """Ego-motion between the previous frame and this one, in the body frame of the previous frame.

    forward, left in metres per frame (or unit-free when ``scaled`` is False); yaw in radians per
    frame, counter-clockwise positive. ``transform`` is the full 6-DoF 4×4 camera transform when
    the estimator knows it (see the module docstring for its direction). ``quality`` is a 0..1
    figure of merit (0: nothing could be estimated, the motion fields are a fallback);
    ``inliers`` counts the measurements that support the estimate (feature inliers, overlapping
    profile columns); ``match_cost`` is the residual of the fit in the estimator's own unit
    (pixels of reprojection error, mean absolute profile difference).
    """

    forward: float
    left: float
    yaw: float
    transform: np.ndarray | None
    quality: float
    inliers: int
    match_cost: float
    scaled: bool = True


# The noise model's settings (docs/egomotion.md, "Uncertainty"): every estimator declares them,
# each with its own defaults (noise_setting), the help written once here.
NOISE_HELP = {
    "sigma_translation": "standard deviation of forward and left per metre moved",
    "sigma_translation_floor": "standard deviation of forward and left per frame however little it moved, m",
    "sigma_yaw": "standard deviation of yaw per radian turned",
    "sigma_yaw_per_m": "standard deviation of yaw per metre moved, rad",
    "sigma_yaw_floor": "standard deviation of yaw per frame however little it turned, rad",
    "sigma_failure_m": "standard deviation of forward and left of a failed frame (quality 0), m",
    "sigma_failure_rad": "standard deviation of yaw of a failed frame (quality 0), rad",
}
FAILURE_MOTIONS = ("zero", "hold")   # what a failed frame reports: no motion, or the last motion


def noise_setting(name: str, default: float):
    """One of the noise model's settings (NOISE_HELP) with an estimator's own default."""
    return setting(default, ge=0.0, help=NOISE_HELP[name])


def failure_motion_setting():
    return setting("zero", choices=FAILURE_MOTIONS,
                   help="what a failed frame reports (quality 0): zero motion, or hold the last motion "
                        "(as LIBVISO2's pipeline does)")


@dataclass(frozen=True)
class NoiseModel:
    """The uncertainty an estimator reports with each increment (EgoMotion.covariance), as
    standard deviations per frame: forward and left each sigma_translation × metres moved +
    sigma_translation_floor; yaw sigma_yaw × radians turned + sigma_yaw_per_m × metres moved +
    sigma_yaw_floor; uncorrelated. A failed frame (quality 0: its motion is a fallback) reports
    sigma_failure_m and sigma_failure_rad. Every estimator's parameters include these, with
    defaults measured against ground truth for that estimator (docs/egomotion.md,
    "Uncertainty"); the experience map weighs the odometry by them."""

    sigma_translation: float = noise_setting("sigma_translation", 0.02)
    sigma_translation_floor: float = noise_setting("sigma_translation_floor", 0.001)
    sigma_yaw: float = noise_setting("sigma_yaw", 0.02)
    sigma_yaw_per_m: float = noise_setting("sigma_yaw_per_m", 0.005)
    sigma_yaw_floor: float = noise_setting("sigma_yaw_floor", 0.0005)
    sigma_failure_m: float = noise_setting("sigma_failure_m", 0.5)
    sigma_failure_rad: float = noise_setting("sigma_failure_rad", 0.2)

    def __post_init__(self) -> None:
        check(self)   # every declared setting of the estimator's parameters within its bounds and choices

    def covariance(self, increment: Increment) -> np.ndarray | None:
        """3×3 covariance of (forward, left, yaw); None for an increment without metric scale."""
        if not increment.scaled:
            return None
        if increment.quality <= 0.0:
            translation, yaw = self.sigma_failure_m, self.sigma_failure_rad
        else:
            distance = math.hypot(increment.forward, increment.left)
            translation = self.sigma_translation * distance + self.sigma_translation_floor
            yaw = self.sigma_yaw * abs(increment.yaw) + self.sigma_yaw_per_m * distance + self.sigma_yaw_floor
        return np.diag([translation ** 2, translation ** 2, yaw ** 2])


def zero_increment(*, inliers: int = 0, match_cost: float = 0.0, scaled: bool = True) -> Increment:
    """No motion, quality 0: the first frame, or a frame nothing could be estimated from."""
    return Increment(0.0, 0.0, 0.0, np.eye(4), 0.0, int(inliers), float(match_cost), scaled)


@runtime_checkable
class Estimator(Protocol):
    """One ego-motion estimator: frames in, one increment per frame out.

    The first frame yields a zero increment. A poor frame (blank, blurred, too few features)
    never raises: it yields a low-quality increment. Only a configuration problem (e.g. a
    stereo estimator given monocular frames) raises EgomotionError.
    """

    name: str

    def estimate(self, frame: Any) -> Increment: ...


# ---------------------------------------------------------------------------------------------
# Conversions


def increment_with_transform(
    transform: np.ndarray, *, quality: float, inliers: int, match_cost: float, scaled: bool = True
) -> Increment:
    forward, left, yaw = increment_from_transform(transform)
    return Increment(forward, left, yaw, transform, float(quality), int(inliers), float(match_cost), scaled)


# ---------------------------------------------------------------------------------------------
# Parameters: frozen dataclasses of declared settings (services.common.settings.setting: help,
# bounds, choices; no pydantic in cores), built from TOML/CLI dicts.

P = TypeVar("P")


def params_from_dict(cls: type[P], values: dict[str, Any] | None, *, where: str) -> P:
    """Build the parameter dataclass ``cls`` from ``values``; an unknown key or a value of the
    wrong type raises EstimatorConfigError naming ``where`` and the key. Types are checked
    against the field annotations (bool, int, float, str, optional float, fixed-length tuple)."""
    values = dict(values or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise EstimatorConfigError(
            f"{where}: unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(fields))}"
        )
    converted = {key: _coerce(value, str(fields[key].type), where=f"{where}: {key}") for key, value in values.items()}
    try:
        return cls(**converted)
    except (TypeError, ValueError) as error:
        raise EstimatorConfigError(f"{where}: {error}") from None
    except ConfigError as error:   # outside the declared bounds or choices (settings.check)
        raise EstimatorConfigError(f"{where}: {str(error).split(': ', 1)[-1]}") from None


def _coerce(value: Any, annotation: str, *, where: str) -> Any:
    optional = "None" in annotation
    if value is None and optional:
        return None
    kind = annotation.replace("| None", "").replace("None |", "").strip()
    is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind == "bool" and not isinstance(value, bool):
        raise EstimatorConfigError(f"{where} must be true or false, got {value!r}")
    if kind == "int" and not (is_number and float(value).is_integer()):
        raise EstimatorConfigError(f"{where} must be an integer, got {value!r}")
    if kind == "float" and not is_number:
        raise EstimatorConfigError(f"{where} must be a number, got {value!r}")
    if kind == "str" and not isinstance(value, str):
        raise EstimatorConfigError(f"{where} must be a string, got {value!r}")
    if kind.startswith("tuple"):
        if not isinstance(value, (list, tuple)) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
        ):
            raise EstimatorConfigError(f"{where} must be a list of numbers, got {value!r}")
        return tuple(value)
    return int(value) if kind == "int" else float(value) if kind == "float" else value
