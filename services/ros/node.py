"""ros2: gridslam as a node of a ROS 2 graph over Zenoh (rmw_zenoh's wire format, or the keys of
zenoh-bridge-ros2dds): odometry, TF, pose, path, experience map and lattice as ROS 2 topics.

    gridslam service ros2 [--ros-domain-id N] [--ros-namespace /gridslam] [--ros-distro jazzy] [--ros2-keys rmw_zenoh]

One node, `gridslam` in `--ros-namespace`, on this process's Zenoh session, so a ROS 2 node
started with `RMW_IMPLEMENTATION=rmw_zenoh_cpp` and the same router sees it (`ros2 node list`,
`ros2 topic echo /gridslam/odom`, RViz). What it publishes is projection.py's; the messages are
messages.py's, the wire format rmw_zenoh.py's and graph.py's (docs/ecosystem.md, "ROS 2 live").

Like the viewer and the Foxglove server it is an observer: it never pushes back on the
pipeline (a deep inbox that drops and counts when full; the lattice newest-only), and its ROS 2
publishers drop rather than block (rmw_zenoh's KEEP_LAST congestion control).
"""

from __future__ import annotations

import argparse
import logging
import time

from pydantic import BaseModel, ConfigDict, Field, create_model

from schemas import FleetPose, GridActivity, GridPose, MapPose, MapUpdate
from services.common import topics as gridslam_topics
from services.common.convert import image_from_msg
from services.common.observe import map_items, observe
from services.common.runtime import RuntimeConfig
from services.common.service import Service
from services.common.settings import add_field_flag, config_fields
from services.ros import projection
from services.ros2wire.graph_settings import add_graph_arguments, graph_flags, graph_params, load_graph_config
from services.ros2wire.messages import IMAGE, MARKER_ARRAY, ODOMETRY, PATH, POSE_WITH_COVARIANCE, TF, RosMessages, yaw_quaternion
from services.ros2wire.rmw_zenoh import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, TF_QOS, GraphParams, Qos, normalise_namespace

log = logging.getLogger(__name__)

INBOX_SIZE = 4096   # as the Foxglove server's
NODE_NAME = "gridslam"
# Topic (relative to the namespace, or absolute) → (ROS type, QoS offered).
TOPICS = {
    projection.ODOM: (ODOMETRY, RELIABLE_QOS),
    projection.TF: (TF, TF_QOS),
    projection.POSE: (POSE_WITH_COVARIANCE, RELIABLE_QOS),
    projection.PATH: (PATH, Qos(depth=1)),
    projection.EXPERIENCE_MAP: (MARKER_ARRAY, LATCHED_QOS),
    projection.GRID_ACTIVITY: (IMAGE, SENSOR_QOS),
}


class _Ros2Fields(BaseModel):
    """Configuration of the ros2 service (table `[ros2]`, env `GRIDSLAM_ROS2_*`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    path_rate_hz: float = Field(4.0, gt=0, le=100, description="nav_msgs/Path messages of the corrected trajectory per second, at most.")
    map_rate_hz: float = Field(1.0, gt=0, le=30, description="Experience-map MarkerArrays per second, at most.")
    fleet: bool = Field(False, description="Also publish every robot's pose in the fleet frame (gridslam/@v1/fleet/<robot>/"
                                           "pose, once joined) as /fleet/<robot>/pose in the shared `map` frame (docs/fleet.md).")


Ros2Config = create_model("Ros2Config", __base__=_Ros2Fields, __doc__=_Ros2Fields.__doc__, **config_fields(GraphParams))


def session_runtime(runtime: RuntimeConfig) -> RuntimeConfig:
    """The runtime with what ROS 2 publishers need of the session (graph.SESSION_CFG) under the user's settings."""
    from services.ros2wire.graph import SESSION_CFG

    return runtime.model_copy(update={"cfg": {**SESSION_CFG, **runtime.cfg}})


class Ros2Service(Service):
    name = "ros2"
    observer = True
    inbox_size = INBOX_SIZE

    def __init__(self, runtime: RuntimeConfig, config, instance: str | None = None):
        super().__init__(session_runtime(runtime), instance)
        self.config = config
        self.params = graph_params(config)
        self.ros = RosMessages(self.params.ros_distro)
        self.projection = projection.Projection(self.ros, 1.0 / config.path_rate_hz, 1.0 / config.map_rate_hz)
        self.node = None
        self.publishers = {}

    def setup(self) -> None:
        from services.ros2wire.graph import RosNode

        p = self.params
        self.node = RosNode(self.session, NODE_NAME, normalise_namespace(p.ros_namespace), p.ros_domain_id,
                            p.ros_distro, p.ros2_keys, hashes=self.ros.rihs01)
        self.publishers = {topic: self.node.publisher(topic, msgtype, qos) for topic, (msgtype, qos) in TOPICS.items()}
        # A seq far back is a new run (the projection starts afresh; common/recovery.py).
        observe(self, {"grid/pose": self.on_grid_pose, "map/pose": self.on_map_pose, "map/update": self.on_map_update,
                       "grid/activity": self.on_grid_activity})
        if self.config.fleet:   # every robot's fleet pose (the fleet map's key space: gridslam/@v1/fleet/<robot>/pose)
            self.subscribe(gridslam_topics.fleet_pose_topic("*"), self.on_fleet_pose, robot=gridslam_topics.FLEET,
                           drop_stale=False, sparse=True)
        log.info("ros2: node %s%s in ROS domain %d (%s, %s keys): %s", self.node.namespace.rstrip("/") + "/", NODE_NAME,
                 p.ros_domain_id, p.ros_distro, p.ros2_keys, ", ".join(e.topic for e in self.node.endpoints))

    def teardown(self) -> None:
        self._put_ros(self.projection.due(time.monotonic(), final=True))
        self.node.close()

    def on_idle(self) -> None:
        self._put_ros(self.projection.due(time.monotonic()))

    def extra_counters(self) -> dict[str, float]:
        return {**super().extra_counters(), "ros_samples": sum(p.published for p in self.publishers.values())}

    def _put_ros(self, messages) -> None:
        for topic, data in messages:
            self.publishers[topic].put(data)

    @staticmethod
    def _stamp(message) -> int:
        return message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec

    def on_grid_pose(self, message: GridPose) -> None:
        twist = message.twist
        self._put_ros(self.projection.grid_pose(
            message.header.seq, self._stamp(message), (message.pose.position.x, message.pose.position.y, message.heading),
            (twist.linear.x, twist.linear.y, twist.linear.z), (twist.angular.x, twist.angular.y, twist.angular.z),
            message.increment_covariance))

    def on_map_pose(self, message: MapPose) -> None:
        placement = message.placement
        self._put_ros(self.projection.map_pose(
            message.header.seq, self._stamp(message), (message.pose.position.x, message.pose.position.y, message.heading),
            message.experience_id, None if placement is None else
            (placement.experience, (placement.dx, placement.dy, placement.dheading))))
        self._put_ros(self.projection.due(time.monotonic()))

    def on_map_update(self, message: MapUpdate) -> None:
        self.projection.map_update(self._stamp(message),
                                   [(e.id, e.x, e.y, e.heading) for e in message.experiences], map_items(message)[1])

    def on_fleet_pose(self, message: FleetPose) -> None:
        """A robot's pose in the fleet frame, once joined: /fleet/<robot>/pose in the shared `map` frame."""
        if not message.joined:
            return
        topic = f"/fleet/{message.header.robot}/pose"
        if topic not in self.publishers:
            self.publishers[topic] = self.node.publisher(topic, POSE_WITH_COVARIANCE, RELIABLE_QOS)
        position = message.pose.position
        self.publishers[topic].put(self.ros.pose_with_covariance(
            self._stamp(message), projection.MAP_FRAME, (position.x, position.y, 0.0), yaw_quaternion(message.heading)))

    def on_grid_activity(self, message: GridActivity) -> None:
        pixels = image_from_msg(message.image)
        if pixels.ndim == 3:
            pixels = pixels.mean(axis=2)
        self._put_ros(self.projection.activity(self._stamp(message), pixels))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_graph_arguments(parser)
    add_field_flag(parser, Ros2Config, "fleet")


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    config = load_graph_config(Ros2Config, {**graph_flags(args), "fleet": args.fleet}, args.config)
    service = Ros2Service(runtime, config, args.instance)
    return service.run()
