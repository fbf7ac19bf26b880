"""foxglove: a Foxglove WebSocket server republishing a run live, from Zenoh, as ROS 2 messages.

Open Foxglove (the desktop app or the web app) → "Open connection" → Foxglove WebSocket →
ws://127.0.0.1:8765. The topics, types and frames are those of run.mcap (messages.py), so a
layout made for a recorded run works on a live one. The server is the official `foxglove-sdk`
(extra `foxglove`): channels with ROS 2 message definitions (`ros2msg`) and CDR payloads.

In front of it a relay (ws_relay.py) accepts both names of the protocol, `foxglove.sdk.v1`
(the SDK's) and `foxglove.websocket.v1` (the npm `@foxglove/ws-protocol` client, Lichtblick
before December 2025, older Foxglove Studio), and gives every client an SDK server of its own.
So a client is sent, when it subscribes to a channel, what the run published on it so far
(`RunHistory`: every pose, transform and loop closure, the newest map, image and camera info),
then every new message: a client that connects late, or after the run has finished, sees the
whole run.

With `--fleet` (`[foxglove] fleet`; docs/fleet.md) it also publishes every robot the fleet map
has joined to the fleet frame: `/fleet/<robot>/pose` (geometry_msgs/PoseWithCovarianceStamped
in frame `map`, the fleet frame, as the ROS 2 node's `--fleet` does) from each
`gridslam/@v1/fleet/<robot>/pose`, and `/fleet/<robot>/path` (nav_msgs/Path, frame `map`: the
poses published since it joined, at most `map_rate_hz` a second). A robot's channels are
advertised when its first joined pose comes, to clients already connected too.

Like the viewer this is an observer: it never pushes back on the pipeline. Its inbox is deep
and a full one drops the sample (counted as `dropped_busy` in its status); camera frames and
lattice snapshots are taken newest-only; the SDK keeps a bounded queue per client and drops a
slow client's oldest messages. Loopback by default: `--host` elsewhere needs `--allow-remote`
(the protocol has no authentication).
"""

from __future__ import annotations

import argparse
import collections
import logging
import math
import threading
import time
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, create_model, field_validator

from schemas import (CameraFrame, EgoMotion, FleetPose, GridActivity, GridPose, LoopClosure, MapPose, MapRoute, MapSnapshot,
                     MapUpdate)
from services.common import codec, topics
from services.common.config import load_config
from services.common.convert import heading_of, image_from_msg, pose_to_matrix
from services.common.errors import ConfigError
from services.common.geometry import planar_from_camera
from services.common.observe import map_items, observe
from services.common.runtime import RuntimeConfig, is_loopback
from services.common.service import Service
from services.common.odometry import DeadReckoning, turn_first
from services.common.recovery import new_run, sent_again
from services.common.settings import add_field_flag, add_flag, config_fields, setting
from services.ros import projection
from services.ros2wire.messages import (
    ACTIVITY_TOPIC, CAMERA_INFO_TOPIC, CAMERA_TOPIC, MAP_FRAME, MARKERS_TOPIC, PATH, POSE_WITH_COVARIANCE, ROUTE_TOPIC,
    TOPICS, MapState,
    RosMessages, camera_jpeg, typestore, yaw_quaternion,
)
from services.ros.ws_relay import SubprotocolRelay

log = logging.getLogger(__name__)

INBOX_SIZE = 4096   # as the viewer's: pose messages are small, newest-only topics queue a marker only
# Topics whose newest message holds all a client needs (the whole map, the last image): a late
# client is sent that one; of every other topic, every message kept.
NEWEST_ONLY = frozenset({"/tf_static", MARKERS_TOPIC, CAMERA_TOPIC, CAMERA_INFO_TOPIC, ACTIVITY_TOPIC, ROUTE_TOPIC})
FLEET_PATH_POINTS = 4000   # a robot's fleet path is thinned to at most this many poses
FLEET_ROBOTS_RESERVED = 4  # a client's queue has room for the history of this many robots' fleet poses


def fleet_pose_topic(robot: str) -> str:
    return f"/fleet/{robot}/pose"


def fleet_path_topic(robot: str) -> str:
    return f"/fleet/{robot}/path"


def newest_only(topic: str) -> bool:
    """Whether a late client needs only the topic's newest message (the whole map, the last image, a whole path)."""
    return topic in NEWEST_ONLY or (topic.startswith("/fleet/") and topic.endswith("/path"))


def check_available() -> None:
    """ConfigError (one line) when the extras the server needs are missing."""
    typestore()
    try:
        import foxglove  # noqa: F401
    except ImportError:
        raise ConfigError("the Foxglove server needs the optional extra 'foxglove': "
                          "pip install 'gridslam[foxglove]'") from None


@dataclass(frozen=True)
class FoxgloveFleetParams:
    """The Foxglove server's fleet setting (declared once: `[foxglove] fleet`, `GRIDSLAM_FOXGLOVE_FLEET`, `--fleet`)."""

    LABEL = "[foxglove]"

    fleet: bool = setting(False, help="Also publish every robot the fleet map has joined (docs/fleet.md) as "
                                      "/fleet/<robot>/pose and /fleet/<robot>/path in the shared frame `map`, the "
                                      "fleet frame.")


class _FoxgloveFields(BaseModel):
    """Configuration of the foxglove service (table `[foxglove]`, env `GRIDSLAM_FOXGLOVE_*`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    allow_remote: bool = Field(False, description="Allow a non-loopback `host` (the Foxglove protocol has no authentication).")
    host: str = Field("127.0.0.1", description="Address the WebSocket server binds to.")
    port: int = Field(8765, ge=0, le=65535, description="WebSocket port (Foxglove's default 8765; 0: any free port).")
    map_rate_hz: float = Field(1.0, gt=0, le=30, description="Experience-map MarkerArrays sent per second, at most.")
    backlog: int = Field(1024, ge=16, description="Messages queued per client beyond the run so far; a slow client "
                                                  "loses its oldest.")
    history: int = Field(20000, ge=1, description="Messages kept per topic (poses, /tf, loop closures; of the map, images "
                                                   "and camera info the newest only) and sent to a client when it "
                                                   "subscribes: the run so far, or the whole finished run.")

    @field_validator("host")
    @classmethod
    def _loopback(cls, value: str, info: ValidationInfo) -> str:
        if not info.data.get("allow_remote") and not is_loopback(value):
            raise ValueError(f"{value} is not a loopback address; the Foxglove protocol has no authentication, so "
                             "serving other machines needs --allow-remote (allow_remote = true)")
        return value


FoxgloveConfig = create_model("FoxgloveConfig", __base__=_FoxgloveFields, __doc__=_FoxgloveFields.__doc__,
                              **config_fields(FoxgloveFleetParams))


class FleetPaths:
    """The fleet's topics (module docstring), pure: fleet poses in, `(topic, ROS type, stamp ns, CDR bytes)`
    out, built by messages.RosMessages. A robot's path holds its poses since it joined; a robot
    whose join the fleet map splits again publishes nothing until it joins again, and its path
    then starts afresh (the old poses are in the fleet frame of a join that was undone)."""

    def __init__(self, ros: RosMessages, period_s: float, max_points: int = FLEET_PATH_POINTS):
        self.ros, self.period_s, self.max_points = ros, period_s, max_points
        self.paths: dict[str, list[tuple[int, float, float, float]]] = {}   # robot → (stamp ns, x, y, heading)
        self.joined: dict[str, bool] = {}
        self.pending: dict[str, int] = {}   # robot → stamp of a path change not sent yet
        self.sent_at = -math.inf

    def pose(self, robot: str, stamp: int, x: float, y: float, heading: float,
             joined: bool) -> list[tuple[str, str, int, bytes]]:
        was_joined = self.joined.get(robot, False)
        self.joined[robot] = joined
        if not joined:
            if was_joined:   # split: the path so far is in a frame it is no longer in
                self.paths[robot] = []
                self.pending.pop(robot, None)
            return []
        if not was_joined:
            self.paths[robot] = []
        self.paths[robot].append((stamp, x, y, heading))
        self.pending[robot] = stamp
        return [(fleet_pose_topic(robot), POSE_WITH_COVARIANCE, stamp, self.ros.pose_with_covariance(
            stamp, projection.MAP_FRAME, (x, y, 0.0), yaw_quaternion(heading)))]

    def due(self, now: float, final: bool = False) -> list[tuple[str, str, int, bytes]]:
        """The paths that changed, once their period has passed (or `final`)."""
        if not self.pending or (not final and now - self.sent_at < self.period_s):
            return []
        messages = []
        for robot, stamp in sorted(self.pending.items()):
            path = self.paths[robot]
            stride = max(1, math.ceil(len(path) / self.max_points))
            poses = path[::stride] if (len(path) - 1) % stride == 0 else path[::stride] + path[-1:]
            messages.append((fleet_path_topic(robot), PATH, stamp, self.ros.path(stamp, projection.MAP_FRAME, poses)))
        self.pending, self.sent_at = {}, now
        return messages


class RunHistory:
    """What the run published on each topic, for a client that subscribes later: up to `limit`
    messages per topic (oldest dropped first), the newest only of the NEWEST_ONLY topics. Pure:
    topics, stamps and payloads."""

    def __init__(self, limit: int):
        self.limit = limit
        self.topics: dict[str, collections.deque[tuple[int, bytes]]] = {}

    def add(self, topic: str, stamp: int, data: bytes) -> None:
        kept = self.topics.get(topic)
        if kept is None:
            kept = self.topics[topic] = collections.deque(maxlen=1 if newest_only(topic) else self.limit)
        kept.append((stamp, data))

    def messages(self, topic: str) -> list[tuple[int, bytes]]:
        return list(self.topics.get(topic, ()))

    def clear(self, topics) -> None:
        """Forget what these topics published."""
        for topic in topics:
            self.topics.pop(topic, None)

    def capacity(self, topics) -> int:
        """The most messages it can hold of these topics."""
        return sum(1 if newest_only(topic) else self.limit for topic in topics)


class ClientServer:
    """One client's own foxglove-sdk server (its context and channels), on a loopback port the
    relay joins the client to. When the client subscribes to a channel it is sent the run's
    history of that topic; live messages reach a channel only after that, so none comes twice
    or is lost in between (the owner's lock orders the two)."""

    def __init__(self, owner: FoxgloveService):
        import foxglove
        import foxglove.websocket

        self.owner = owner
        self.context = foxglove.Context()
        self.channels = {}
        for topic, msgtype in {**TOPICS, **owner.extra_topics}.items():   # a copy: the main thread adds to it
            self.add_channel(topic, msgtype)
        self.replayed: set[str] = set()   # topics the client subscribed to and was sent the history of
        self.closed = False
        self._closing = threading.Lock()
        listener = self

        class Listener(foxglove.websocket.ServerListener):   # SDK threads
            def on_subscribe(self, client, channel) -> None:
                listener.on_subscribe(channel.topic)

            def on_unsubscribe(self, client, channel) -> None:
                with owner.lock:
                    listener.replayed.discard(channel.topic)

        config = owner.config
        reserved = FLEET_ROBOTS_RESERVED * (config.history + 1) if config.fleet else 0   # robots that join later
        self.server = foxglove.start_server(
            name=f"gridslam {owner.robot}", host="127.0.0.1", port=0, context=self.context, server_listener=Listener(),
            message_backlog_size=config.backlog + owner.history.capacity({**TOPICS, **owner.extra_topics}) + reserved)
        self.port = self.server.port

    def add_channel(self, topic: str, msgtype: str) -> None:
        """A channel of the client's server (a robot's fleet topic: advertised to the connected client)."""
        import foxglove

        self.channels[topic] = foxglove.Channel(topic, message_encoding="cdr", context=self.context,
                                                schema=foxglove.Schema(name=msgtype, encoding="ros2msg",
                                                                       data=self.owner.msgdefs[msgtype]))

    def on_subscribe(self, topic: str) -> None:
        if topic not in self.channels:
            return
        with self.owner.lock:
            for stamp, data in self.owner.history.messages(topic):
                self.channels[topic].log(data, log_time=stamp)
            self.replayed.add(topic)

    def log(self, topic: str, stamp: int, data: bytes) -> None:   # under the owner's lock
        if topic in self.replayed:
            self.channels[topic].log(data, log_time=stamp)

    def close(self) -> None:
        """Once, from whichever thread comes first (the relay's when the client leaves, the
        service's when it stops)."""
        with self._closing:
            if self.closed:
                return
            self.closed = True
        self.owner.forget(self)
        self.server.stop()


class FoxgloveService(Service):
    name = "foxglove"
    observer = True
    inbox_size = INBOX_SIZE

    def __init__(self, runtime: RuntimeConfig, config: FoxgloveConfig, instance: str | None = None):
        super().__init__(runtime, instance)
        self.config = config
        check_available()

        self.ros = RosMessages()
        fleet_types = (POSE_WITH_COVARIANCE, PATH) if config.fleet else ()   # the fleet's channels' types
        self.msgdefs = {msgtype: self.ros.msgdef(msgtype).encode() for msgtype in {*TOPICS.values(), *fleet_types}}
        self.extra_topics: dict[str, str] = {}   # topics beyond TOPICS: the fleet's, as robots join
        self.fleet = FleetPaths(self.ros, 1.0 / config.map_rate_hz) if config.fleet else None
        self.history = RunHistory(config.history)
        self.lock = threading.Lock()             # guards history and clients (main, relay and SDK threads)
        self.clients: list[ClientServer] = []
        try:   # bound now: a busy port is an error before anything starts
            self.relay = SubprotocolRelay(config.host, config.port, self.open_client)
        except OSError as error:
            raise ConfigError(f"foxglove: cannot serve on {config.host}:{config.port}: {error.strerror or error}") from None
        self.sent = 0
        self.map_state = MapState()
        self.map_pending: int | None = None     # stamp of a map change not sent yet
        self.map_sent_at = 0.0
        self.dead_reckoning: DeadReckoning | None = None   # of the egomotion increments
        self.pose_seq: dict[str, int] = {}   # pose topic → its newest seq
        self._snapshot: MapSnapshot | None = None   # the map as fetched at start, until the main thread applies it

    def open_client(self) -> ClientServer:   # a relay thread: a client is connecting
        client = ClientServer(self)
        with self.lock:
            self.clients.append(client)
            for topic, msgtype in self.extra_topics.items():   # a fleet topic that came meanwhile
                if topic not in client.channels:
                    client.add_channel(topic, msgtype)
        return client

    def forget(self, client: ClientServer) -> None:
        with self.lock:
            if client in self.clients:
                self.clients.remove(client)

    @property
    def url(self) -> str:
        return f"ws://{self.config.host if ':' not in self.config.host else f'[{self.config.host}]'}:{self.relay.port}"

    def run(self) -> int:
        # Clients may connect while a router is awaited; they get the run as it comes.
        self.relay.start()
        try:
            return super().run()
        finally:
            self.close_server()

    def close_server(self) -> None:
        self.relay.stop()
        with self.lock:
            clients = list(self.clients)
        for client in clients:
            client.close()

    def setup(self) -> None:
        # drop_stale=False: a seq far back is a new run, shown afresh (_fresh).
        observe(self, {"egomotion": self.on_egomotion, "grid/pose": self.on_grid_pose, "map/pose": self.on_map_pose,
                       "map/update": self.on_map_update, "loop/closure": self.on_loop_closure,
                       "camera/frame": self.on_camera_frame, "grid/activity": self.on_grid_activity,
                       "map/route": self.on_map_route})
        # A map already built when this service starts: fetch it once (map/update then keeps it).
        self.session.get(topics.key(self.robot, "map/snapshot"), self._on_snapshot, timeout=5.0)
        if self.fleet is not None:   # every robot's pose in the fleet frame (the fleet map's key space)
            self.subscribe(topics.fleet_pose_topic("*"), self.on_fleet_pose, robot=topics.FLEET, drop_stale=False,
                           sparse=True)
        log.info("foxglove serving %s", self.url)

    def teardown(self) -> None:
        self.close_server()

    def on_idle(self) -> None:
        self._take_snapshot()
        self._send_map_if_due()
        if self.fleet is not None:
            self._log_fleet(self.fleet.due(time.monotonic()))

    def extra_counters(self) -> dict[str, float]:
        return {**super().extra_counters(), "messages_sent": self.sent, "clients": len(self.clients),
                "clients_refused": self.relay.refused}

    # ----------------------------------------------------------------- pipeline topics (main thread)
    def _log(self, stamp: int, *messages: tuple[str, bytes]) -> None:
        with self.lock:
            for topic, data in messages:
                self.history.add(topic, stamp, data)
                for client in self.clients:
                    client.log(topic, stamp, data)
                self.sent += 1

    def _fresh(self, topic: str, seq: int) -> bool:
        """Whether a pose is new (common/recovery.py's rules). A frame sent again (a stage's
        outputs replayed after a reconnection, the frames in flight resent to a restarted stage
        or after a stall) the clients have already (False). A new run on the robot starts the
        pipeline's history afresh (True); the fleet's topics, of the fleet map, stay."""
        last = self.pose_seq.get(topic)
        if sent_again(last, seq):
            return False
        if new_run(last, seq):
            with self.lock:
                self.history.clear(TOPICS)
            self.pose_seq.clear()
            self.dead_reckoning = None
        self.pose_seq[topic] = seq
        return True

    @staticmethod
    def _stamp(message) -> int:
        stamp = message.header.stamp
        return stamp.sec * 1_000_000_000 + stamp.nanosec

    def on_egomotion(self, message: EgoMotion) -> None:
        # Dead reckoning of the increments as egomotion.tum has it, the way the viewer and the
        # gridcells baseline do it (turned for the integrators' turn-first order).
        seq = message.header.seq
        if not self._fresh("egomotion", seq):
            return
        if self.dead_reckoning is None:
            self.dead_reckoning = DeadReckoning()
        step = message.increment
        pose = self.dead_reckoning.step(*turn_first(step.forward, step.left, step.yaw), step.yaw).pose
        stamp = self._stamp(message)
        self._log(stamp, *self.ros.planar_pose("egomotion", stamp, pose.x, pose.y, pose.heading))

    def on_grid_pose(self, message: GridPose) -> None:
        if not self._fresh("grid/pose", message.header.seq):
            return
        stamp = self._stamp(message)
        self._log(stamp, *self.ros.planar_pose("gridcells", stamp, message.pose.position.x, message.pose.position.y,
                                               message.heading))

    def on_map_pose(self, message: MapPose) -> None:
        if not self._fresh("map/pose", message.header.seq):
            return
        stamp = self._stamp(message)
        self._log(stamp, *self.ros.planar_pose("map", stamp, message.pose.position.x, message.pose.position.y,
                                               message.heading))

    def on_map_route(self, message: MapRoute) -> None:
        """A route asked of the map (`map/route`, gridslam map route's query): one nav_msgs/Path
        on /gridslam/route in the map frame, as the viewer draws it."""
        stamp = self._stamp(message)
        poses = [(stamp, pose.position.x, pose.position.y, heading_of(pose)) for pose in message.poses]
        self._log(stamp, (ROUTE_TOPIC, self.ros.path(stamp, MAP_FRAME, poses)))

    def on_map_update(self, message: MapUpdate) -> None:
        self._take_snapshot()
        if self.map_state.apply(*map_items(message)):
            self.map_pending = self._stamp(message)
        self._send_map_if_due()

    def on_loop_closure(self, message: LoopClosure) -> None:
        stamp = self._stamp(message)
        fields = message.model_dump(exclude={"header", "schema_version"})
        self._log(stamp, self.ros.closure(stamp, fields))

    def on_fleet_pose(self, message: FleetPose) -> None:
        position = message.pose.position
        stamp = self._stamp(message)
        self._log_fleet(self.fleet.pose(message.header.robot, stamp, position.x, position.y, message.heading,
                                        message.joined))
        self._log_fleet(self.fleet.due(time.monotonic()))

    def _log_fleet(self, messages: list[tuple[str, str, int, bytes]]) -> None:
        """The fleet's messages; a topic new to the run gets its channel on every client first."""
        for topic, msgtype, _, _ in messages:
            if topic not in self.extra_topics:
                with self.lock:
                    self.extra_topics[topic] = msgtype
                    for client in self.clients:
                        client.add_channel(topic, msgtype)
        with self.lock:
            for topic, _, stamp, data in messages:
                self.history.add(topic, stamp, data)
                for client in self.clients:
                    client.log(topic, stamp, data)
                self.sent += 1

    def on_camera_frame(self, message: CameraFrame) -> None:
        stamp = self._stamp(message)
        jpeg, scale = camera_jpeg(image_from_msg(message.left), message.left.encoding)
        messages = [self.ros.camera_image(stamp, jpeg), self.ros.static_transforms(stamp)]
        info = message.camera_info
        if info is not None:
            messages.append(self.ros.camera_info(stamp, info.fx * scale, info.fy * scale, info.cx * scale,
                                                 info.cy * scale, round(message.left.width * scale),
                                                 round(message.left.height * scale)))
        if message.ground_truth is not None:
            messages += self.ros.planar_pose("groundtruth", stamp, *planar_from_camera(pose_to_matrix(message.ground_truth)))
        self._log(stamp, *messages)

    def on_grid_activity(self, message: GridActivity) -> None:
        stamp = self._stamp(message)
        pixels = image_from_msg(message.image)
        if pixels.ndim == 3:
            pixels = pixels.mean(axis=2)
        self._log(stamp, self.ros.activity(stamp, pixels))

    # ----------------------------------------------------------------- the map
    def _send_map_if_due(self) -> None:
        now = time.monotonic()
        if self.map_pending is None or now - self.map_sent_at < 1.0 / self.config.map_rate_hz:
            return
        stamp, self.map_pending, self.map_sent_at = self.map_pending, None, now
        self._log(stamp, self.ros.markers(stamp, self.map_state))

    def _take_snapshot(self) -> None:
        snapshot, self._snapshot = self._snapshot, None
        if snapshot is not None and self.map_state.apply(*map_items(snapshot)):
            self.map_pending = self._stamp(snapshot)

    def _on_snapshot(self, reply) -> None:   # a Zenoh thread: the main thread applies it (_take_snapshot)
        if reply.ok is None:
            return
        try:
            snapshot = codec.decode(reply.ok.payload.to_bytes(), MapSnapshot, str(reply.ok.encoding))
        except codec.CodecError as error:
            self.counters.decode_errors += 1
            log.warning("foxglove: dropped map snapshot: %s", error)
            return
        self._snapshot = snapshot


def add_arguments(parser: argparse.ArgumentParser) -> None:
    for name in ("host", "port", "allow_remote"):
        add_field_flag(parser, FoxgloveConfig, name)
    add_flag(parser, FoxgloveFleetParams, "fleet", action="store_true", default=None)


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    config = load_config(FoxgloveConfig, "foxglove", config_file=args.config,
                         overrides={"host": args.host, "port": args.port, "allow_remote": args.allow_remote,
                                    "fleet": args.fleet})
    service = FoxgloveService(runtime, config, args.instance)
    print(f"gridslam foxglove: {service.url}", flush=True)
    return service.run()
