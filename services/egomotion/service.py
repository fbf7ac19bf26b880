"""egomotion: estimate the camera's motion between consecutive frames (scanline, stereo, mono, passthrough).

One instance (`instances` = 1, the default) runs the estimator frame after frame, as `gridslam
odometry` does. Several instances may share one robot's frames (docs/pipeline.md, "Sharded
ego-motion"), each told how many run (`instances` > 1): each
receives every frame and keeps the newest ones, estimates the frames of its share
(services/egomotion/shards.py: blocks of `shard_block` seqs, each run by a fresh estimator primed
with the frames before it, so that every instance computes the same increments), and says which
frame each increment starts from (EgoMotion.previous_seq): gridcells puts them back in order. An
instance joins the shares with a liveliness token `gridslam/@v1/<robot>/shard/egomotion/<instance>/<since>`
once it holds the frames it needs; the shares follow the tokens alive. A frame sent again (the
source re-sends the frames in flight when no acknowledgement comes: an instance died or joined)
is estimated by the instance whose share holds it now, or its earlier increment is published again.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading

import zenoh

from schemas import CameraFrame, EgoMotion, PlanarIncrement
from services.common import topics
from services.common.convert import image_from_msg, pose_to_matrix
from services.common.runtime import RuntimeConfig
from services.common.service import Service
from services.common.settings import add_field_flag, add_flag
from services.egomotion import ESTIMATORS, SHARD_SETTINGS, EgomotionConfig, make_estimator, resolve_estimator, resolve_sharding
from services.egomotion.base import params_from_dict
from services.egomotion.mono import MonoParams
from services.egomotion.shards import BlockEstimation, FrameByFrame, FrameHistory, ShardParams, block_owner
from services.common.frames import Camera, Frame

log = logging.getLogger(__name__)

HISTORY_FRAMES = 64    # frames kept: more than the source keeps in flight plus a block and its primers


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

    def __init__(self, runtime: RuntimeConfig, estimator_name: str, params: dict, instance: str | None = None,
                 shard_block: int | None = None):
        """`shard_block`: frames per block, as every instance sharing the robot's frames runs them
        (shards.block_size); None: this instance is the robot's only one, frame after frame."""
        super().__init__(runtime, instance)
        self.estimator_name = estimator_name
        self.params = params
        self.shard_block = shard_block
        self.noise = params_from_dict(ESTIMATORS[estimator_name][1], params, where=f"{estimator_name} parameters")
        # The estimator is built with the calibration of its first frame (of each block, sharded).
        make = lambda frame: make_estimator(estimator_name, frame.camera, params)  # noqa: E731
        if shard_block is None:
            self.history = None
            self.blocks: FrameByFrame | BlockEstimation = FrameByFrame(make, frame_of=frame_from_message)
        else:
            self.history = FrameHistory(max(HISTORY_FRAMES, 4 * shard_block))
            self.blocks = BlockEstimation(make, shard_block, frame_of=frame_from_message)
        self.estimated = 0
        self._members: dict[str, tuple[str, int]] = {}   # shard token key → (instance, since); Zenoh threads write it
        self._members_lock = threading.Lock()
        self._token = None
        self._warned_shared = False

    @property
    def alone(self) -> bool:
        """Whether this instance was started as the robot's only one (frame after frame)."""
        return self.shard_block is None

    def setup(self) -> None:
        self.subscribe("camera/frame", self.on_frame, on_stale=self.on_frame_again)
        self.watch(topics.shard_key(self.robot, self.name, "*", "*"), self._on_member)

    def _on_member(self, sample: zenoh.Sample) -> None:   # a Zenoh thread
        key = str(sample.key_expr)
        try:
            _, _, instance, since = topics.parse_shard_key(key)
        except ValueError:
            return
        with self._members_lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._members.pop(key, None)
            else:
                self._members[key] = (instance, since)
        if self.alone and sample.kind != zenoh.SampleKind.DELETE and instance != self.instance and not self._warned_shared:
            self._warned_shared = True
            log.warning("egomotion/%s runs frame after frame as the robot's only instance (instances = 1), but "
                        "instance %s shares the frames in blocks: their increments differ and both publish; give every "
                        "instance the same --instances N (GRIDSLAM_EGOMOTION_INSTANCES; docs/pipeline.md)",
                        self.instance, instance)

    def members(self) -> dict[str, float]:
        """Every instance sharing the frames → its `since` (this one's: infinite until it holds enough frames)."""
        with self._members_lock:
            tokens = list(self._members.values())
        members: dict[str, float] = {}
        for instance, since in tokens:
            members[instance] = min(since, members.get(instance, math.inf))
        if self.history is None:
            members[self.instance] = 0
        else:
            members[self.instance] = math.inf if self.history.since is None else self.history.since
        return members

    def on_frame(self, message: CameraFrame) -> None:
        if self.alone:
            self.estimate(message)
            return
        seq = message.header.seq
        self.history.add(seq, message)
        if self._token is None and self.history.since is not None:
            self._token = self.session.liveliness().declare_token(
                topics.shard_key(self.robot, self.name, self.instance, self.history.since))
            self._entities.append(self._token)
            log.info("egomotion/%s takes a share of the frames from seq %d (blocks of %d)", self.instance,
                     self.history.since, self.shard_block)
        if block_owner(seq, self.shard_block, self.members()) == self.instance:
            self.estimate(message)

    def on_frame_again(self, message: CameraFrame) -> None:
        """A frame sent again: its increment again if this instance published one, else (its share
        changed since) estimated now when it is this instance's."""
        seq = message.header.seq
        if self.replay_outputs(seq):
            return
        if self.alone:   # not published: the estimator refused it, or it is older than the estimator's last
            last = self.blocks.last_fed
            if last is None or seq > last:
                self.estimate(message)
            return
        if self.history.add(seq, message) and block_owner(seq, self.shard_block, self.members()) == self.instance:
            self.estimate(message)

    def estimate(self, message: CameraFrame) -> None:
        # A frame this estimator cannot use (stereo given a mono frame: EgomotionError) is
        # counted and dropped by the base class; the next increment starts from the frame before.
        estimate = self.blocks.estimate(message.header.seq, message if self.alone else self.history)
        increment = estimate.increment
        covariance = self.noise.covariance(increment)
        self.estimated += 1
        self.publish("egomotion", EgoMotion(
            header=message.header.model_copy(update={"frame_id": "base_link"}), previous_seq=estimate.previous_seq,
            increment=PlanarIncrement(forward=increment.forward, left=increment.left, yaw=increment.yaw),
            transform=[float(v) for v in increment.transform.ravel()] if increment.transform is not None else None,
            quality=min(max(float(increment.quality), 0.0), 1.0), inliers=int(increment.inliers),
            match_cost=max(float(increment.match_cost), 0.0), scaled=increment.scaled, estimator=self.estimator_name,
            covariance=[float(v) for v in covariance.ravel()] if covariance is not None else None,
        ))

    def extra_counters(self) -> dict[str, float]:
        return {**super().extra_counters(), "estimated": self.estimated, "estimated_again": self.blocks.rebuilt,
                "shard_members": len(self.members())}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_field_flag(parser, EgomotionConfig, "estimator")
    parser.add_argument("--preset", help="estimator parameters for a dataset: nubot, kitti, stlucia, synthetic, campus, "
                                         "or a preset file")
    add_flag(parser, MonoParams, "camera_height_m", flag="--camera-height", dest="camera_height", metavar="M")
    for name in SHARD_SETTINGS:   # --instances, --shard-block
        add_flag(parser, ShardParams, name, metavar="N")


def estimator_settings(args: argparse.Namespace) -> tuple[str, dict]:
    """Estimator name and parameters (services.egomotion.resolve_estimator) from the flags."""
    return resolve_estimator(args.estimator, args.preset, args.config, getattr(args, "camera_height", None))


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    name, params = estimator_settings(args)
    _, block = resolve_sharding(name, args.instances, args.shard_block, args.config)
    return EgomotionService(runtime, name, params, args.instance, block).run()
