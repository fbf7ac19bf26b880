"""Camera calibration files: our own small TOML format, and KITTI's ``calib.txt``.

Our format (documented in docs/sources.md) is a flat TOML table for a rectified pinhole
camera or stereo pair::

    fx = 493.86945        # focal length along x, pixels (required)
    fy = 493.86945        # focal length along y, pixels (required)
    cx = 320.33392        # principal point x, pixels (required)
    cy = 244.18816        # principal point y, pixels (required)
    baseline = 0.11996    # left-to-right camera distance, metres (optional, 0 = monocular)
    width = 640           # image size in pixels (optional; checked against the images)
    height = 480

Any other key is an error, so a typo never passes silently.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from services.common.config import read_toml
from services.common.frames import Camera, SourceError

# A monocular image folder, video or camera without a calibration gets a pinhole camera with this
# horizontal field of view (`--fov`, source key `fov`): about a phone's main camera or a webcam
# (60–78°; KITTI's grey cameras: 82°). The mono estimator and the closure geometry then work; the
# run says the camera was assumed.
DEFAULT_FOV_DEG = 65.0

REQUIRED_KEYS = ("fx", "fy", "cx", "cy")
OPTIONAL_KEYS = ("baseline", "width", "height")
CALIBRATION_KEYS = REQUIRED_KEYS + OPTIONAL_KEYS


def assumed_camera(width: int, height: int, fov_deg: float = DEFAULT_FOV_DEG) -> Camera:
    """A pinhole camera for ``width``×``height`` images with a horizontal field of view of
    ``fov_deg``: square pixels, the principal point at the image centre, no distortion."""
    if not 0 < fov_deg < 180:
        raise SourceError(f"field of view {fov_deg:g}° is not between 0 and 180°")
    focal = (width / 2) / math.tan(math.radians(fov_deg) / 2)
    return Camera(fx=focal, fy=focal, cx=(width - 1) / 2, cy=(height - 1) / 2, baseline=0.0, width=width, height=height)


def camera_from_mapping(values: Mapping[str, Any], where: str) -> Camera:
    """A Camera from a table holding only calibration keys; ``where`` names the file in errors."""
    unknown = sorted(set(values) - set(CALIBRATION_KEYS))
    if unknown:
        raise SourceError(f"{where}: unknown calibration key {unknown[0]!r} (expected {', '.join(CALIBRATION_KEYS)})")
    missing = [key for key in REQUIRED_KEYS if key not in values]
    if missing:
        raise SourceError(f"{where}: calibration key {missing[0]!r} is missing (required: {', '.join(REQUIRED_KEYS)})")
    numbers: dict[str, float] = {}
    for key, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise SourceError(f"{where}: calibration key {key!r} is not a finite number: {value!r}")
        numbers[key] = float(value)
    for key in ("fx", "fy"):
        if numbers[key] <= 0:
            raise SourceError(f"{where}: calibration key {key!r} must be positive, got {numbers[key]}")
    if numbers.get("baseline", 0.0) < 0:
        raise SourceError(f"{where}: calibration key 'baseline' must not be negative, got {numbers['baseline']}")
    for key in ("width", "height"):
        if key in numbers and (numbers[key] < 0 or numbers[key] != int(numbers[key])):
            raise SourceError(f"{where}: calibration key {key!r} must be a whole number of pixels, got {values[key]!r}")
    return Camera(
        fx=numbers["fx"],
        fy=numbers["fy"],
        cx=numbers["cx"],
        cy=numbers["cy"],
        baseline=numbers.get("baseline", 0.0),
        width=int(numbers.get("width", 0)),
        height=int(numbers.get("height", 0)),
    )


def read_calibration(path: str | Path) -> Camera:
    """Read a calibration file of our TOML format (module docstring)."""
    return camera_from_mapping(read_toml(path, "calibration file", SourceError), str(path))


def write_calibration(path: str | Path, camera: Camera) -> None:
    """Write ``camera`` in our TOML format (so a synthetic or converted dataset carries its calibration)."""
    lines = [f"{key} = {float(getattr(camera, key))!r}" for key in ("fx", "fy", "cx", "cy", "baseline")]
    lines += [f"{key} = {getattr(camera, key)}" for key in ("width", "height") if getattr(camera, key)]
    Path(path).write_text("\n".join(lines) + "\n")


def read_kitti_calibration(path: Path, width: int = 0, height: int = 0) -> Camera:
    """The left camera's intrinsics and the stereo baseline from a KITTI ``calib.txt``.

    Lines are 12 numbers (a row-major 3×4 projection matrix), either named (``P0: ...``, the
    official odometry layout, which also holds P2, P3 and Tr) or bare (first line P0, second
    P1, as in our flat clips). fx, fy, cx, cy come from P0; the baseline from P1's
    x-translation, P1[0,3] = −fx·b (KITTI devkit, rectified projection matrices).
    """
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise SourceError(f"{path}: calibration file not found") from None
    except (OSError, UnicodeDecodeError) as error:
        raise SourceError(f"{path}: cannot read calibration: {error}") from None
    named: dict[str, np.ndarray] = {}
    bare: list[np.ndarray] = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        name, colon, rest = line.partition(":")
        name, fields = (name.strip(), rest.split()) if colon else (f"P{len(bare)}", line.split())
        try:
            values = np.array([float(field) for field in fields])
        except ValueError:
            raise SourceError(f"{path}: line {number}: {name} is not a list of numbers") from None
        if values.size != 12:
            raise SourceError(f"{path}: line {number}: {name} has {values.size} values, expected 12 (a 3×4 matrix)")
        if colon:
            named[name] = values.reshape(3, 4)
        else:
            bare.append(values.reshape(3, 4))
    p0 = named.get("P0", bare[0] if bare else None)
    p1 = named.get("P1", bare[1] if len(bare) > 1 else None)
    if p0 is None:
        raise SourceError(f"{path}: no projection matrix P0")
    if p0[0, 0] <= 0 or p0[1, 1] <= 0:
        raise SourceError(f"{path}: P0 has a non-positive focal length")
    baseline = float(-p1[0, 3] / p1[0, 0]) if p1 is not None and p1[0, 0] > 0 else 0.0
    return Camera(
        fx=float(p0[0, 0]),
        fy=float(p0[1, 1]),
        cx=float(p0[0, 2]),
        cy=float(p0[1, 2]),
        baseline=baseline,
        width=width,
        height=height,
    )
