"""Key expressions (DESIGN.md, "Key expressions"): `gridslam/@v1/<robot>/<topic>`."""

from __future__ import annotations

from schemas import (
    CameraFrame, EgoMotion, GridActivity, GridPose, LoopClosure, MapPose, MapRoute, MapSnapshot, MapUpdate, ServiceStatus,
    ViewTemplate,
)
from schemas.base import Message

PREFIX = "gridslam/@v1"

# Every pipeline topic and the message it carries.
TOPICS: dict[str, type[Message]] = {
    "camera/frame": CameraFrame,
    "egomotion": EgoMotion,
    "grid/pose": GridPose,
    "grid/activity": GridActivity,
    "view/template": ViewTemplate,
    "loop/closure": LoopClosure,
    "map/pose": MapPose,
    "map/update": MapUpdate,
    "map/snapshot": MapSnapshot,
    "map/route": MapRoute,
    "status": ServiceStatus,
}


def model_of(topic: str) -> type[Message]:
    """The message model carried by `topic` (status/<service>/<instance> carries ServiceStatus)."""
    return ServiceStatus if topic.startswith("status/") else TOPICS[topic]


def key(robot: str, topic: str) -> str:
    """Key expression of `topic` for `robot`, e.g. key('robot0', 'grid/pose')."""
    return f"{PREFIX}/{robot}/{topic}"


def health_key(robot: str, service: str, instance: str) -> str:
    """Liveliness token of one running service instance."""
    return f"{PREFIX}/{robot}/health/{service}/{instance}"


def shard_key(robot: str, service: str, instance: str, since: int | str) -> str:
    """Liveliness token of an instance that takes a share of the frames (sharded egomotion): it
    can run any block that starts at seq `since` or later, holding the frames before it (docs/pipeline.md)."""
    return f"{PREFIX}/{robot}/shard/{service}/{instance}/{since}"


def parse_shard_key(key_expr: str) -> tuple[str, str, str, int]:
    """(robot, service, instance, since) of a shard token's key."""
    parts = key_expr.split("/")
    if len(parts) != 7 or "/".join(parts[:2]) != PREFIX or parts[3] != "shard" or not parts[6].isdigit():
        raise ValueError(f"{key_expr!r} is not a gridslam shard key")
    return parts[2], parts[4], parts[5], int(parts[6])


def status_key(robot: str, service: str, instance: str) -> str:
    """Status topic and queryable of one running service instance."""
    return f"{PREFIX}/{robot}/status/{service}/{instance}"


def parse_health_key(key_expr: str) -> tuple[str, str, str]:
    """(robot, service, instance) of a liveliness token's key."""
    parts = key_expr.split("/")
    if len(parts) != 6 or "/".join(parts[:2]) != PREFIX or parts[3] != "health":
        raise ValueError(f"{key_expr!r} is not a gridslam health key")
    return parts[2], parts[4], parts[5]
