"""gridslam wire messages: one pydantic model per message (DESIGN.md, "Messages")."""

from schemas.base import SCHEMA_VERSION, Header, Image, PlanarIncrement, Point, Pose, Quaternion, Time, Twist, Vector3
from schemas.messages import (
    MESSAGES, CameraFrame, CameraInfo, EgoMotion, Experience, GridActivity, GridPose, Link, LoopClosure,
    MapPose, MapRoute, MapSnapshot, MapUpdate, ServiceStatus, ViewTemplate,
)

__all__ = [
    "SCHEMA_VERSION", "MESSAGES", "Header", "Image", "PlanarIncrement", "Point", "Pose", "Quaternion", "Time",
    "Twist", "Vector3", "CameraFrame", "CameraInfo", "EgoMotion", "Experience", "GridActivity", "GridPose",
    "Link", "LoopClosure", "MapPose", "MapRoute", "MapSnapshot", "MapUpdate", "ServiceStatus", "ViewTemplate",
]
