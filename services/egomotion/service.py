"""egomotion: estimate the camera's motion between consecutive frames (scanline, stereo, mono, passthrough)."""

from __future__ import annotations

import argparse
import logging
import os

from schemas import CameraFrame, EgoMotion, PlanarIncrement
from services.common.config import read_toml
from services.common.convert import image_from_msg, pose_to_matrix
from services.common.runtime import RuntimeConfig
from services.common.service import Service
from services.common.errors import ConfigError
from services.egomotion import ESTIMATORS, load_estimator_config, make_estimator
from services.egomotion.base import Estimator, params_from_dict
from services.source.frames import Camera, Frame

log = logging.getLogger(__name__)


def frame_from_message(message: CameraFrame) -> Frame:
    """The pure core's Frame of a wire CameraFrame."""
    left = image_from_msg(message.left)
    info = message.camera_info
    camera = Camera(fx=info.fx, fy=info.fy, cx=info.cx, cy=info.cy, baseline=info.baseline,
                    width=left.shape[1], height=left.shape[0]) if info is not None else None
    odometry = message.odometry
    return Frame(
        seq=message.header.seq, stamp=message.header.stamp.to_seconds(), left=left,
        right=image_from_msg(message.right) if message.right is not None else None, camera=camera,
        ground_truth=pose_to_matrix(message.ground_truth) if message.ground_truth is not None else None,
        odometry=(odometry.forward, odometry.left, odometry.yaw) if odometry is not None else None,
    )


class EgomotionService(Service):
    name = "egomotion"

    def __init__(self, runtime: RuntimeConfig, estimator_name: str, params: dict, instance: str | None = None):
        super().__init__(runtime, instance)
        self.estimator_name = estimator_name
        self.params = params
        self.estimator: Estimator | None = None   # built on the first frame, which brings the calibration

    def setup(self) -> None:
        self.subscribe("camera/frame", self.on_frame)

    def on_frame(self, message: CameraFrame) -> None:
        frame = frame_from_message(message)
        # A frame this estimator cannot use (stereo given a mono frame: EgomotionError) is
        # counted and dropped by the base class; the gap shows downstream through seq.
        if self.estimator is None:
            self.estimator = make_estimator(self.estimator_name, frame.camera, self.params)
        increment = self.estimator.estimate(frame)
        covariance = self.estimator.params.covariance(increment)
        self.publish("egomotion", EgoMotion(
            header=message.header.model_copy(update={"frame_id": "base_link"}),
            increment=PlanarIncrement(forward=increment.forward, left=increment.left, yaw=increment.yaw),
            transform=[float(v) for v in increment.transform.ravel()] if increment.transform is not None else None,
            quality=min(max(float(increment.quality), 0.0), 1.0), inliers=int(increment.inliers),
            match_cost=max(float(increment.match_cost), 0.0), scaled=increment.scaled, estimator=self.estimator_name,
            covariance=[float(v) for v in covariance.ravel()] if covariance is not None else None,
        ))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--estimator", choices=["scanline", "stereo", "mono", "passthrough"],
                        help="ego-motion estimator (default: the preset's, else scanline)")
    parser.add_argument("--preset", help="estimator parameters for a dataset: nubot, kitti, stlucia, synthetic, campus, "
                                         "or a preset file")


def estimator_settings(args: argparse.Namespace) -> tuple[str, dict]:
    """Estimator name and parameters from the preset < the --config file's [egomotion] table
    (`estimator = "..."` and one sub-table per estimator) < GRIDSLAM_EGOMOTION_ESTIMATOR < --estimator."""
    default, params = load_estimator_config(args.preset)
    table = read_toml(args.config).get("egomotion", {}) if args.config else {}
    for estimator, values in table.items():
        if estimator in ESTIMATORS:
            params[estimator].update(values)
        elif estimator != "estimator":
            raise ConfigError(f"{args.config}: [egomotion] unknown key {estimator!r}")
    name = args.estimator or os.environ.get("GRIDSLAM_EGOMOTION_ESTIMATOR") or table.get("estimator") or default or "scanline"
    if name not in ESTIMATORS:
        raise ConfigError(f"unknown estimator {name!r} (available: {', '.join(ESTIMATORS)})")
    params_from_dict(ESTIMATORS[name][1], params[name], where=f"{name} parameters")   # fail at start, not at frame 1
    return name, params[name]


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    name, params = estimator_settings(args)
    return EgomotionService(runtime, name, params, args.instance).run()
