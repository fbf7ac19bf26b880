"""What a run assumes, said before it starts: which ego-motion estimator runs, which camera it
works with (given, or assumed from a field of view) and whether its scale is metric (and from
what) or arbitrary; and whether the estimator can work on the source at all. A run that cannot
work fails here, in one line with a hint that fits the case, instead of stalling for a minute
(DESIGN.md, "Fail fast, say what was assumed")."""

from __future__ import annotations

import math
from dataclasses import dataclass

from services.common.config import preset_applies
from services.common.errors import ConfigError
from services.common.frames import Frame, FrameSource
from services.egomotion import resolve_estimator


class StageInputError(ConfigError):
    """A stage of the run cannot work on its input (the message says why and what to do)."""


@dataclass(frozen=True)
class Assumptions:
    estimator: str
    camera: str           # the camera the run works with, in words
    scale: str            # metric (from what) or arbitrary
    metric: bool

    def lines(self) -> list[str]:
        return [f"egomotion: {self.estimator}; scale {self.scale}", f"camera: {self.camera}"]

    def record(self) -> dict:
        return {"estimator": self.estimator, "camera": self.camera, "scale": self.scale, "metric_scale": self.metric}


def describe_camera(frames: FrameSource) -> str:
    camera = frames.camera
    if camera is None and getattr(frames, "camera_note", None):   # a live stream's camera comes with it
        return frames.camera_note
    if camera is None:
        return "none (no calibration: the estimators and closure geometry that need one cannot run)"
    size = f"{camera.width}×{camera.height}, " if camera.width else ""
    if getattr(frames, "camera_assumed", False):
        fov = math.degrees(2 * math.atan(camera.width / (2 * camera.fx)))
        return (f"assumed: a pinhole with a {fov:.0f}° horizontal field of view ({size}f = {camera.fx:.1f} px, centred; "
                "--fov DEG or --calibration FILE to say otherwise)")
    stereo = f", stereo baseline {camera.baseline:g} m" if camera.baseline > 0 else ""
    return f"calibrated ({size}fx = {camera.fx:.1f}, fy = {camera.fy:.1f}, cx = {camera.cx:.1f}, cy = {camera.cy:.1f} px{stereo})"


def assess(estimator: str | None, preset: str | None, config_file, camera_height: float | None, spec: str,
           frames: FrameSource) -> Assumptions:
    """The run's assumptions, or StageInputError when its estimator cannot work on ``frames``."""
    egomotion_preset = preset if preset and preset_applies("egomotion", preset) else None
    name, params = resolve_estimator(estimator, egomotion_preset, config_file, camera_height)
    whose = "" if estimator else (f" (the {preset} preset's estimator)" if egomotion_preset else " (the default)")
    first: Frame = frames[0] if not getattr(frames, "live", False) else None
    camera = frames.camera
    if name == "stereo" and (camera is None or camera.baseline <= 0 or (first is not None and first.right is None)):
        what = "has no stereo calibration" if first is not None and first.right is not None else "is monocular"
        raise StageInputError(f"the stereo estimator{whose} needs a stereo pair with its calibration, and {spec} {what}: "
                              + ("give --calibration FILE with its baseline" if what.startswith("has") else
                                 "use --egomotion mono (a camera is assumed when none is given) or --egomotion scanline"))
    if name == "mono" and camera is None and not getattr(frames, "camera_expected", False):
        raise StageInputError(f"the mono estimator{whose} needs camera intrinsics and {spec} has none: give --calibration "
                              "FILE (fx, fy, cx, cy)" + (" or --camera-info-topic" if spec.startswith("rosbag:") else ""))
    if name == "passthrough" and first is not None and first.odometry is None and first.ground_truth is None:
        raise StageInputError(f"the passthrough estimator{whose} passes on the frames' odometry or ground truth, and "
                              f"{spec} has neither: use --egomotion mono or scanline"
                              + (", or --odom-topic" if spec.startswith("rosbag:") else ""))
    return Assumptions(name, describe_camera(frames), *_scale(name, params, camera, first, preset, camera_height))


def _scale(name: str, params: dict, camera, first: Frame | None, preset: str | None, camera_height) -> tuple[str, bool]:
    if name == "stereo":
        return f"metric (from the stereo baseline, {camera.baseline:g} m)", True
    if name == "passthrough":
        return "metric (the frames' own odometry or ground truth)", True
    if name == "mono":
        source = params.get("scale_source", "auto")
        height = float(params.get("camera_height_m", 0.0))
        if source in ("auto", "odometry") and first is not None and first.odometry is not None:
            return "metric (from the frames' odometry)", True
        if source in ("auto", "ground") and height > 0:
            origin = "--camera-height" if camera_height else f"the {preset} preset" if preset else "the config"
            return f"metric (from the camera's height above the ground, {height:g} m, {origin})", True
        return "arbitrary (1 unit of length per frame: no odometry, no camera height; give --camera-height M)", False
    # scanline: speed is a per-dataset scaling of image change (vtrans_scaling).
    if preset and "vtrans_scaling" in params:
        return f"metric only as far as the {preset} preset calibrates it for its dataset (scanline's vtrans_scaling)", True
    return ("arbitrary (scanline's speed scaling, vtrans_scaling, is not calibrated for this data: a preset for a known "
            "dataset, or --egomotion mono with --camera-height)"), False
