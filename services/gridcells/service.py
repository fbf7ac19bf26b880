"""gridcells: integrate ego-motion with the grid-cell attractor network (or dead reckoning)."""

from __future__ import annotations

import argparse
import logging
import math
import os
from pathlib import Path

import cv2
import numpy as np

from schemas import EgoMotion, GridActivity, GridPose, Twist, Vector3
from services.common.codec import decode, encode
from services.common.config import load_config
from services.common.errors import DataError, PersistenceError
from services.common.convert import image_to_msg, planar_pose
from services.common.runtime import RuntimeConfig
from services.common.service import Service
from services.common.settings import add_flag, add_renamed_flag
from services.common.stages import STEP_SOURCES, GridStageParams
from services.gridcells.config import GridCellsConfig
from services.gridcells.integrator import DeadReckoning, GridCellIntegrator, auto_velocity_scale, turn_first
from services.gridcells.network import GridCellError, NetworkParams

log = logging.getLogger(__name__)

# Increments beyond these are no vehicle's motion over one frame (100 m is 360 km/h at 1 frame/s;
# a turn beyond half a revolution is ambiguous between two frames). Integrated, they would drive
# the pose or the network to overflow and spoil every later frame, so they are rejected.
MAX_STEP_M = 100.0
MAX_TURN_RAD = math.pi


def make_integrator(config: GridCellsConfig):
    """The pure integrator a config describes."""
    if config.integrator == "deadreckoning":
        return DeadReckoning()
    params = NetworkParams(n=config.neurons)
    scale = (auto_velocity_scale(np.array([config.typical_speed]), params)
             if config.velocity_scale == "auto" else float(config.velocity_scale))
    log.info("grid-cell network n=%d, decoder %s, step %s, %d module(s), heading %s, velocity scale %.4g units/m", config.neurons,
             config.decoder, config.step, config.modules, config.heading, scale)
    return GridCellIntegrator(params, decoder=config.decoder, velocity_scale=scale, step=config.step, modules=config.modules,
                              heading=config.heading)


def save_checkpoint(path: Path, checkpoint: dict, seq: int, stamp: float | None) -> None:
    """Write atomically (a kill mid-write leaves the previous checkpoint): arrays and numbers only."""
    arrays = {name: np.asarray(value) for name, value in checkpoint.items() if value is not None}
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as handle:
            np.savez(handle, seq=seq, stamp=np.nan if stamp is None else stamp, **arrays)
        os.replace(tmp, path)
    except OSError as error:
        raise PersistenceError(f"{path}: cannot write the grid-cell checkpoint ({error.strerror or error})") from None


def load_checkpoint(path: Path) -> tuple[dict, int, float | None]:
    try:
        with np.load(path, allow_pickle=False) as data:
            values = {name: data[name] for name in data.files}
    except (OSError, ValueError, KeyError) as error:
        raise DataError(f"{path}: unreadable grid-cell checkpoint ({error}); delete it to start afresh") from None
    seq, stamp = int(values.pop("seq")), float(values.pop("stamp"))
    values.setdefault("previous", None)
    return values, seq, None if np.isnan(stamp) else stamp


class GridCellsService(Service):
    name = "gridcells"
    exclusive = True   # the network's state runs through every frame

    def __init__(self, runtime: RuntimeConfig, config: GridCellsConfig, instance: str | None = None):
        super().__init__(runtime, instance)
        self.config = config
        self.integrator = make_integrator(config)
        grid = config.integrator == "grid"
        self.provenance = {"decoder": config.decoder if grid else None, "step_source": config.step if grid else "odometry",
                           "heading_model": config.heading if grid else "sum", "modules": config.modules if grid else 0}
        self.frames = 0
        self.previous_stamp: float | None = None
        self.resumed_at: int | None = None   # frames up to this one are already integrated
        if config.checkpoint is not None and config.checkpoint.exists():
            checkpoint, self.resumed_at, self.previous_stamp = load_checkpoint(config.checkpoint)
            last_pose = checkpoint.pop("last_pose", None)
            self.integrator.restore(checkpoint)
            if last_pose is not None:
                # The pose of the checkpoint's frame may have died with the process that computed
                # it: when that frame comes again, it is published again (Service.replay_outputs).
                self.remember_output(self.resumed_at, "grid/pose", decode(last_pose.tobytes(), GridPose))
            log.info("gridcells resumed from %s after frame %d", config.checkpoint, self.resumed_at)

    def setup(self) -> None:
        # Increments come out of order from several egomotion instances: each waits for the one
        # it follows. Those integrated before a restart (the checkpoint holds them) are stale.
        self.subscribe("egomotion", self.on_egomotion, follows=lambda message: message.previous_seq,
                       handled_up_to=self.resumed_at)

    def on_egomotion(self, message: EgoMotion) -> None:
        increment = message.increment
        if max(abs(increment.forward), abs(increment.left)) > MAX_STEP_M or abs(increment.yaw) > MAX_TURN_RAD:
            raise GridCellError(f"increment (forward {increment.forward:.3g} m, left {increment.left:.3g} m, "
                                f"yaw {increment.yaw:.3g} rad) exceeds {MAX_STEP_M:g} m or {MAX_TURN_RAD:.4g} rad per frame")
        # The message's translation is in the body frame before the frame's yaw (SE(2)
        # composition, as the egomotion stage's own trajectory is integrated); the integrators
        # turn first, then move (the authors' order).
        step = self.integrator.step(*turn_first(increment.forward, increment.left, increment.yaw), increment.yaw)
        stamp = message.header.stamp.to_seconds()
        dt = stamp - self.previous_stamp if self.previous_stamp is not None else 0.0
        self.previous_stamp = stamp
        twist = Twist(linear=Vector3(x=step.step_length / dt), angular=Vector3(z=increment.yaw / dt)) if dt > 0 else Twist()
        header = message.header.model_copy(update={"frame_id": "odom"})
        pose = GridPose(
            header=header, pose=planar_pose(step.pose.x, step.pose.y, step.pose.heading), twist=twist,
            heading=step.pose.heading, lattice_shift=step.shift, step_length=step.step_length,
            saturated=step.saturated, integrator=self.config.integrator, **self.provenance,
            increment_covariance=self.increment_covariance(message.covariance, step.step_length),
        )
        if self.config.checkpoint is not None:
            # Saved before the pose leaves: a restart then publishes it again when the frame comes again.
            save_checkpoint(self.config.checkpoint, {**self.integrator.checkpoint(),
                                                     "last_pose": np.frombuffer(encode(pose), np.uint8)},
                            message.header.seq, stamp)
        self.publish("grid/pose", pose)
        self.frames += 1
        every = self.config.activity_every
        if every and self.config.integrator == "grid" and self.frames % every == 0:
            self.publish("grid/activity", self.activity(header, step.shift))

    def increment_covariance(self, covariance: list[float] | None, step_length: float) -> list[float] | None:
        """The ego-motion's covariance of the increment, plus (for the network) the sideways error
        of a step whose direction is read from the lattice."""
        if covariance is None or self.config.integrator != "grid":
            return covariance
        sideways = (step_length * self.config.direction_noise) ** 2
        return [value + (sideways if index == 4 else 0.0) for index, value in enumerate(covariance)]

    def activity(self, header, shift) -> GridActivity:
        field = np.asarray(self.integrator.activity, dtype=np.float32)
        size = self.config.activity_size
        small = cv2.resize(field, (size, size), interpolation=cv2.INTER_AREA)
        peak = float(small.max())
        scaled = np.zeros_like(small, dtype=np.uint8) if peak <= 0 else np.clip(small * (255.0 / peak), 0, 255).astype(np.uint8)
        return GridActivity(header=header, image=image_to_msg(scaled), neurons=field.shape[0], max_rate=peak,
                            lattice_shift=shift)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    for name in ("integrator", "decoder"):
        add_flag(parser, GridStageParams, name)
    add_flag(parser, GridStageParams, "step", flag="--step-source")
    add_renamed_flag(parser, "--step", "--step-source", dest="step", choices=STEP_SOURCES)
    add_flag(parser, GridStageParams, "modules", metavar="N")
    add_flag(parser, GridStageParams, "heading")
    parser.add_argument("--velocity-scale", help="network units per metre, or auto (default)")
    parser.add_argument("--preset", help="dataset preset (services/gridcells/presets/)")
    parser.add_argument("--checkpoint", type=Path, help="state file written every frame; a restart resumes from it")


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    config = load_config(GridCellsConfig, "gridcells", preset=args.preset, config_file=args.config, overrides={
        "integrator": args.integrator, "decoder": args.decoder, "step": args.step, "modules": args.modules,
        "heading": args.heading, "velocity_scale": args.velocity_scale,
        "checkpoint": args.checkpoint})
    return GridCellsService(runtime, config, args.instance).run()
