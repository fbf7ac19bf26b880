"""One valid instance of every wire message, for codec and transport tests."""

from __future__ import annotations

import numpy as np

from schemas import (
    CameraFrame, CameraInfo, EgoMotion, Experience, GridActivity, GridPose, Header, Link, LoopClosure, MapPose,
    MapRoute, MapSnapshot, MapUpdate, PlanarIncrement, Point, ServiceStatus, Time, ViewTemplate,
)
from schemas.base import Message
from services.common.convert import image_to_msg, planar_pose


def header(seq: int = 7, frame_id: str = "camera") -> Header:
    return Header(seq=seq, stamp=Time.from_seconds(12.25), frame_id=frame_id, robot="robot0")


def sample_messages(seq: int = 7) -> list[Message]:
    rng = np.random.default_rng(seq)
    grey = rng.integers(0, 256, (24, 32), dtype=np.uint8)
    experiences = [Experience(id=0, x=0.0, y=0.0, heading=0.0, template_id=0, frame=0),
                   Experience(id=1, x=1.5, y=-0.5, heading=0.3, template_id=2, frame=4)]
    links = [Link(source=0, target=1, dx=1.5, dy=-0.5, dheading=0.3, frame=4)]
    return [
        CameraFrame(header=header(seq), left=image_to_msg(grey), right=image_to_msg(grey[::-1].copy()),
                    camera_info=CameraInfo(fx=400.0, fy=400.0, cx=16.0, cy=12.0, baseline=0.12),
                    ground_truth=planar_pose(1.0, 2.0, 0.5), odometry=PlanarIncrement(forward=0.1, left=0.0, yaw=0.01)),
        EgoMotion(header=header(seq), increment=PlanarIncrement(forward=0.2, left=-0.01, yaw=0.05),
                  transform=list(np.eye(4).ravel()), quality=0.9, inliers=120, match_cost=0.4, estimator="stereo"),
        GridPose(header=header(seq, "odom"), pose=planar_pose(3.0, -1.0, 1.0), heading=1.0, lattice_shift=(1.5, -0.25),
                 step_length=0.2, integrator="grid"),
        GridActivity(header=header(seq), image=image_to_msg(grey), neurons=128, max_rate=3.5, lattice_shift=(1.0, 0.0)),
        ViewTemplate(header=header(seq), template_id=3, is_new=False, distance=0.04, relative_angle=-0.1,
                     matched_frame=2, template_count=4),
        LoopClosure(header=header(seq), frame=seq, matched_frame=1, matched_template=1, votes=7),
        MapPose(header=header(seq, "map"), pose=planar_pose(2.9, -1.1, 0.9), heading=0.9, experience_id=1),
        MapUpdate(header=header(seq, "map"), experiences=experiences, links=links, experience_count=2, link_count=1),
        MapSnapshot(header=header(seq, "map"), experiences=experiences, links=links),
        MapRoute(header=header(seq, "map"), start=Point(x=0.1, y=0.0), goal=Point(x=1.4, y=-0.4), experiences=[0, 1],
                 poses=[planar_pose(0.0, 0.0, 0.0), planar_pose(1.5, -0.5, 0.3)], length=1.58, found=True),
        ServiceStatus(header=header(seq), service="gridcells", instance="host-1", state="running", received=10,
                      published=10, decode_errors=1, gaps=0, stale=0, uptime=3.5),
    ]
