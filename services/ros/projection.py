"""gridslam's poses and map as a ROS 2 robot's topics (REP-105): the pure core of the live node
(node.py). Numbers in, `(topic, CDR bytes)` out, built by messages.RosMessages (the one place
where gridslam messages become ROS 2 messages); the adapter decodes and publishes.

- `odom` (nav_msgs/Odometry, frame `odom`, child `base_link`) and `/tf` odom → base_link, from
  each grid-cell pose, stamped with the frame's capture time. The pose's covariance is the
  increments' covariances propagated along the path (first order: P ← F P Fᵀ + G Q Gᵀ, the
  turn-first step of the integrators: heading first, then the move along the new heading).
- `/tf` map → odom, from each map pose: the map frame's correction of the odometry,
  T(map→odom) = T(map→base_link) · T(odom→base_link)⁻¹ at the same frame.
- `pose` (geometry_msgs/PoseWithCovarianceStamped, frame `map`), with the odometry's covariance
  (the map stage publishes none of its own).
- `path` (nav_msgs/Path, frame `map`): every frame placed on its experience as the map now has
  it (the experience map's corrected trajectory), at most every `path_period_s` and at the end.
  A frame's experience and offset are the map's own record of it (`MapPose.placement`), so the
  path does not depend on whether an update of the map reached the node before or after the
  frame's pose (different keys, which Zenoh may deliver in either order); a map pose without one
  (a localisation on a saved map, which does not move it) is placed against the experience as
  last heard.
- `experience_map` (visualization_msgs/MarkerArray), at most every `map_period_s` and at the end.
- `grid_activity` (sensor_msgs/Image, mono8) of the lattice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from services.common.geometry import between, compose
from services.common.recovery import new_run, sent_again
from services.ros2wire.messages import MapState, RosMessages, planar_covariance_6x6, yaw_quaternion

ODOM_FRAME, BASE_FRAME, MAP_FRAME, GRID_FRAME = "odom", "base_link", "map", "grid"
# Topic names, relative to the node's namespace (absolute ones stay).
ODOM, TF, POSE, PATH, EXPERIENCE_MAP, GRID_ACTIVITY = "odom", "/tf", "pose", "path", "experience_map", "grid_activity"
RECENT_FRAMES = 256   # grid poses kept to pair with the map pose of the same frame


def propagate(covariance: np.ndarray, previous, pose, increment_covariance) -> np.ndarray:
    """The pose covariance after one turn-first step from `previous` to `pose` (planar), with
    the step's body-frame (forward, left, yaw) covariance `increment_covariance`."""
    forward, left, _ = between((previous[0], previous[1], pose[2]), pose)   # the move, in the new heading
    c, s = math.cos(pose[2]), math.sin(pose[2])
    turn = np.array([-s * forward - c * left, c * forward - s * left, 1.0])   # ∂(x, y, θ)/∂θ, ∂/∂yaw alike
    F = np.eye(3)
    F[:, 2] = turn
    G = np.zeros((3, 3))
    G[:2, :2] = [[c, -s], [s, c]]
    G[:, 2] = turn
    Q = np.asarray(increment_covariance, dtype=float).reshape(3, 3)
    return F @ covariance @ F.T + G @ Q @ G.T


@dataclass
class Projection:
    """The live node's state (module docstring). Stamps are ns; `now` is a monotonic clock in s."""

    ros: RosMessages
    path_period_s: float = 0.25
    map_period_s: float = 1.0
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    odom_pose: tuple[float, float, float] | None = None
    grid_poses: dict[int, tuple[float, float, float]] = field(default_factory=dict)   # seq → odom pose
    experiences: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    frames: list[tuple[int, int, tuple[float, float, float]]] = field(default_factory=list)  # (stamp, experience, offset)
    map_state: MapState = field(default_factory=MapState)
    path_pending: int | None = None   # stamp of a change not sent yet
    map_pending: int | None = None
    path_sent_at: float = -math.inf
    map_sent_at: float = -math.inf
    last_seq: int | None = None       # newest grid pose's
    last_map_seq: int | None = None   # newest map pose's
    waiting: dict[int, tuple[int, tuple[float, float, float]]] = field(default_factory=dict)   # map poses before their grid pose

    def grid_pose(self, seq: int, stamp: int, pose, linear=(0.0, 0.0, 0.0), angular=(0.0, 0.0, 0.0),
                  increment_covariance=None) -> list[tuple[str, bytes]]:
        """`odom` and `/tf` odom → base_link of one grid-cell pose (x, y, heading)."""
        if sent_again(self.last_seq, seq):   # a stage replayed its outputs: already published
            return []
        if new_run(self.last_seq, seq):      # the odometry starts afresh
            self.reset()
        self.last_seq = seq
        if self.odom_pose is not None and increment_covariance is not None:
            self.covariance = propagate(self.covariance, self.odom_pose, pose, increment_covariance)
        self.odom_pose = tuple(float(v) for v in pose)
        self.grid_poses[seq] = self.odom_pose
        while len(self.grid_poses) > RECENT_FRAMES:
            del self.grid_poses[next(iter(self.grid_poses))]
        x, y, heading = self.odom_pose
        rotation = yaw_quaternion(heading)
        messages = [(ODOM, self.ros.odometry(stamp, ODOM_FRAME, BASE_FRAME, (x, y, 0.0), rotation,
                                             planar_covariance_6x6(self.covariance), linear, angular)),
                    (TF, self.ros.transforms(stamp, [(ODOM_FRAME, BASE_FRAME, (x, y, 0.0), rotation)]))]
        if seq in self.waiting:   # its map pose came first (they reach the node by different routes)
            messages.append(self._correction(*self.waiting.pop(seq), self.odom_pose))
        return messages

    def _correction(self, stamp: int, pose, odom) -> tuple[str, bytes]:
        """/tf map → odom: T(map→base) · T(odom→base)⁻¹."""
        correction = compose(pose, between(odom, (0.0, 0.0, 0.0)))
        return TF, self.ros.transforms(stamp, [(MAP_FRAME, ODOM_FRAME, (correction[0], correction[1], 0.0),
                                                yaw_quaternion(correction[2]))])

    def map_pose(self, seq: int, stamp: int, pose, experience: int, placement=None) -> list[tuple[str, bytes]]:
        """`/tf` map → odom and `pose` of one map pose; the frame joins the path, placed by
        `placement` (experience, offset: the map's record of the frame) where it has one."""
        pose = tuple(float(v) for v in pose)
        if sent_again(self.last_map_seq, seq):   # already placed
            return []
        self.last_map_seq = seq
        messages = []
        odom = self.grid_poses.get(seq)
        if odom is not None:
            messages.append(self._correction(stamp, pose, odom))
        else:
            self.waiting[seq] = (stamp, pose)
            while len(self.waiting) > RECENT_FRAMES:
                del self.waiting[next(iter(self.waiting))]
        messages.append((POSE, self.ros.pose_with_covariance(stamp, MAP_FRAME, (pose[0], pose[1], 0.0),
                                                             yaw_quaternion(pose[2]),
                                                             planar_covariance_6x6(self.covariance))))
        if placement is not None:
            experience, offset = placement[0], tuple(float(v) for v in placement[1])
            # an experience not announced yet: where this frame puts it, until an update places it
            self.experiences.setdefault(experience, compose(pose, between(offset, (0.0, 0.0, 0.0))))
        else:
            offset = between(self.experiences.setdefault(experience, pose), pose)
        self.frames.append((stamp, experience, offset))
        self.path_pending = stamp
        return messages

    def map_update(self, stamp: int, experiences, links) -> None:
        """Experiences created or moved `[(id, x, y, heading)]`, links created `[(source, target,
        kind)]` (common.observe's link kinds)."""
        for experience, x, y, heading in experiences:
            self.experiences[experience] = (float(x), float(y), float(heading))
        if self.map_state.apply([(e, x, y) for e, x, y, _ in experiences], links):
            self.map_pending = stamp
            self.path_pending = stamp

    def activity(self, stamp: int, pixels: np.ndarray) -> list[tuple[str, bytes]]:
        return [(GRID_ACTIVITY, self.ros.mono_image(stamp, GRID_FRAME, pixels))]

    def due(self, now: float, final: bool = False) -> list[tuple[str, bytes]]:
        """The path and the experience map when they changed and their period has passed (or `final`)."""
        messages = []
        if self.path_pending is not None and (final or now - self.path_sent_at >= self.path_period_s):
            messages.append((PATH, self.ros.path(self.path_pending, MAP_FRAME, self.trajectory())))
            self.path_pending, self.path_sent_at = None, now
        if self.map_pending is not None and (final or now - self.map_sent_at >= self.map_period_s):
            messages.append((EXPERIENCE_MAP, self.ros.marker_array(self.map_pending, self.map_state)))
            self.map_pending, self.map_sent_at = None, now
        return messages

    def trajectory(self) -> list[tuple[int, float, float, float]]:
        """(stamp, x, y, heading) of every frame on its experience as the map now has it."""
        return [(stamp, *compose(self.experiences[experience], offset)) for stamp, experience, offset in self.frames]

    def reset(self) -> None:
        self.covariance = np.zeros((3, 3))
        self.odom_pose = None
        self.grid_poses.clear()
        self.waiting.clear()
        self.last_map_seq = None
        self.frames.clear()
        self.experiences.clear()
        self.map_state = MapState()
        self.path_pending = self.map_pending = None
