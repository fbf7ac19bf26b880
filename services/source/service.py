"""source: publish camera frames from a dataset, a video, a live camera or the synthetic world.

Offline replay loses nothing: pipeline topics use congestion control BLOCK, and the source keeps
at most `window` frames in flight, counting a frame done when its `ack_topic` message (by
default `map/pose`, the last stage) arrives. With `adaptive_window` (the default) it keeps fewer:
as many as keep the slowest stage busy, worked out from its send and acknowledgement times
(window.py), so that frames do not wait in queues for no throughput; the frames in flight, their
acknowledgements and their resends are replay.py's. A live camera keeps at most
`live_window` frames in flight and then takes the camera's newest frame: the frames the pipeline
has no time for are dropped at the camera, so none waits in a queue on the way and latency stays
bounded.

With `wait_for`, the first frame waits until those services' health tokens are on the network
(started all at once, as docker-compose does, the pipeline is not there yet). With `loop`, the
source starts again at its first frame after its last, for ever (a demo that keeps running):
`seq` and the stamps go on from the last lap's, so the pipeline sees one long run through the
same world and keeps building the same map (laps.py).

With `resume`, a source restarted in a running pipeline (a container brought back by its
restart policy) goes on where the pipeline is, instead of at its first frame, which every stage
has handled and would drop: before its first frame it asks the running services for their
status, and starts at the last frame they have all handled (the smallest `seq` of those that
handled one), sending it again first as `gridslam run` does when it restarts its source; a
looping source goes on in that frame's lap.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, create_model

from schemas import CameraFrame, CameraInfo, PlanarIncrement
from schemas.base import Message
from services.common.config import load_config
from services.common.convert import image_to_msg, matrix_to_pose
from services.common.health import live_services, statuses
from services.common.runtime import RuntimeConfig
from services.common.service import Service
from services.common.settings import add_field_flag, add_renamed_flag, config_fields
from services.common.topics import TOPICS
from services.source.calibration import DEFAULT_FOV_DEG
from services.common.frames import Frame, FrameSource
from services.source.laps import Laps
from services.source.replay import Pacer, ReplayController, ReplayParams, Resend
from services.source.spec import (BAG_KEYS, BagParams, add_bag_arguments, add_world_arguments, bag_settings, open_source,
                                  parse_world_flags, world_keys)
from services.source.synthetic import WorldConfig
from services.source.window import AdaptiveWindow, WindowParams

log = logging.getLogger(__name__)

# After camera/frame regains a subscriber (the router came back), wait this long before re-sending
# the frames in flight (replay.py).
RECONNECT_SETTLE_S = 0.5
RESUME_QUERY_S = 2.0       # how long a resuming source waits for the services' status replies


class _SourceSettings(BaseModel):
    """Configuration of the source service (table `[source]`, env `GRIDSLAM_SOURCE_*`); the
    synthetic world's settings (`laps`, `speed`, ... : spec.world_keys()) are keys of it too."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    source: str = Field(description="What to read: kitti:PATH, stereo:PATH, images:PATH, video:FILE, camera:N, synthetic:SEED, "
                                    "rosbag:PATH, ros2:TOPIC.")
    preset: str | None = Field(None, description="Source preset (calibration and settings): nubot, kitti, stlucia, synthetic, campus, "
                                                  "irat, or a preset file (docs/sources.md).")
    calibration: Path | None = Field(None, description="Calibration TOML file (fx, fy, cx, cy, baseline); overrides the preset's.")
    fov: float | None = Field(
        None, gt=0, lt=180, description=f"Horizontal field of view, degrees, of the pinhole camera assumed for an image folder, "
                                        f"video or live camera without a calibration (default: the preset's, else "
                                        f"{DEFAULT_FOV_DEG:g}).")
    mono: bool = Field(False, description="Publish only the left image of a stereo source.")
    start: int = Field(0, ge=0, description="First frame index.")
    origin: int | None = Field(
        None, ge=0, description="Frame whose camera pose is the ground truth's origin (default: the first frame sent); "
                                "a source restarted mid-run keeps the run's origin.")
    stop: int | None = Field(None, ge=0, description="Frame index to stop before (default: the end).")
    step: int = Field(1, ge=1, description="Take every step-th frame (the stride).")
    rate: float = Field(0.0, ge=0.0, description="Frames per second to publish at; 0: as fast as the window allows.")
    window: int = Field(8, ge=0, description="Frames in flight awaiting ack_topic before the source waits; 0: no flow control. "
                                             "With adaptive_window, the most it keeps in flight.")
    adaptive_window: bool = Field(
        True, description="Replay: keep only as many frames in flight (at most `window`) as keep the slowest stage busy, "
                          "from the measured delivery rate and the latency of frames sent into an empty pipeline "
                          "(docs/pipeline.md); false: always `window`. Not for a live camera (live_window).")
    live_window: int = Field(
        2, ge=0, description="The same for a live camera, which then takes its newest frame: the frames the pipeline "
                             "has no time for are dropped at the camera, not queued on the way (0: no flow control).")
    ack_topic: str = Field("map/pose", description="Topic whose messages mark a frame as processed by the pipeline.")
    resend_after: float = Field(
        5.0, gt=0, description="Seconds without an acknowledgement after which the frames in flight are sent again "
                               "(a service restarted downstream lost them; services that already handled a frame "
                               "replay their outputs instead of computing them again).")
    resend_acknowledged: int = Field(
        17, ge=0, description="Acknowledged frames sent again, oldest first, before the frames in flight when those are "
                              "re-sent: a restarted egomotion rebuilds the block in hand from them, so its increments "
                              "equal an uninterrupted run's (a block of `shard_block` frames and its 2 primers: 17 covers "
                              "mono's 16, stereo's 4 needs 5; docs/pipeline.md).")
    exit_at_end: bool = Field(True, description="Exit once the last frame is acknowledged (or sent, without flow control).")
    loop: bool = Field(
        False, description="After the last frame start again at the first, for ever; seq and stamps go on from the last "
                           "lap's (meant for a closed route such as the synthetic world's).")
    wait_for: list[str] = Field(
        default_factory=list, description="Services whose health tokens must all be on the network before the first "
                                          "frame (e.g. egomotion, gridcells, loopclosure, expmap).")
    resume: bool = Field(
        False, description="Before the first frame, ask the running services for the last frame they have all handled "
                           "and start there (sent again first), in its lap when looping: a source restarted in a running "
                           "pipeline goes on where it is. Datasets, video files and the synthetic world.")

    def world(self) -> dict[str, Any]:
        """The synthetic world settings given here (they override the preset's)."""
        return {key: getattr(self, key) for key in world_keys() if getattr(self, key) is not None}


def _world_fields() -> dict[str, Any]:
    defaults = {field.name: field.default for field in dataclasses.fields(WorldConfig)}
    return {key: (kind | None, Field(None, description=f"Synthetic world: {key} (default {defaults[key]!r}); "
                                                        f"overrides the preset's (docs/sources.md)."))
            for key, kind in world_keys().items()}


SourceConfig = create_model("SourceConfig", __base__=_SourceSettings, __doc__=_SourceSettings.__doc__, **_world_fields(),
                            **config_fields(BagParams))


def frame_message(frame: Frame, header) -> CameraFrame:
    """The wire message of one source frame."""
    camera = frame.camera
    return CameraFrame(
        header=header,
        left=image_to_msg(frame.left),
        right=image_to_msg(frame.right) if frame.right is not None else None,
        camera_info=CameraInfo(fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy, baseline=camera.baseline)
        if camera is not None else None,
        ground_truth=matrix_to_pose(frame.ground_truth) if frame.ground_truth is not None else None,
        odometry=PlanarIncrement(forward=frame.odometry[0], left=frame.odometry[1], yaw=frame.odometry[2])
        if frame.odometry is not None else None,
    )


class SourceService(Service):
    name = "source"
    idle_timeout = 0.0

    def __init__(self, runtime: RuntimeConfig, config: SourceConfig, frames: FrameSource, instance: str | None = None,
                 graph=None):
        super().__init__(runtime, instance)
        self.graph = graph          # GraphParams of a ros2: source (the ROS 2 graph it listens to)
        self.ros_node = None
        self.config = config
        self.frames = frames
        self.live = bool(getattr(frames, "live", False))
        window = config.live_window if self.live else config.window
        # The window that follows the pipeline (replay only; a live camera keeps live_window).
        flow = AdaptiveWindow(WindowParams(maximum=window)) if window and config.adaptive_window and not self.live else None
        self.replay = ReplayController(ReplayParams(window=window, live=self.live, resend_after=config.resend_after,
                                                    resend_acknowledged=config.resend_acknowledged,
                                                    reconnect_settle=RECONNECT_SETTLE_S), flow)
        self.pacer = Pacer(config.rate)
        self.feed = Laps(frames, loop=config.loop, step=config.step)   # the frames as sent, lap after lap (laps.py)
        self.finished = False
        self.completed = False      # every frame sent and acknowledged: `finished` in the status
        self.pipeline_ready = not config.wait_for  # the services of wait_for were seen
        self.pipeline_checked = 0.0
        self.pipeline_wait_said = False
        self.resume_checked = False
        self.ready: CameraFrame | None = None       # the next frame, read ahead while the window is full

    @property
    def window(self) -> int:
        """The configured window (live_window for a live camera; 0: no flow control)."""
        return self.replay.params.window

    @property
    def flow(self) -> AdaptiveWindow | None:
        return self.replay.flow

    @property
    def sent(self) -> int:
        return self.replay.frames_sent

    @property
    def resent(self) -> int:
        return self.replay.resent

    @property
    def laps(self) -> int:
        """Laps completed (loop)."""
        return self.feed.laps

    def setup(self) -> None:
        if hasattr(self.frames, "subscriptions"):
            self._listen_to_ros2()
        if self.window:
            if self.config.ack_topic not in TOPICS:
                raise ValueError(f"ack_topic {self.config.ack_topic!r} is not a pipeline topic")
            # (A live camera's frames skip the ones it dropped: no gap to count on their acknowledgements.)
            self.subscribe(self.config.ack_topic, self.on_ack, drop_stale=False, sparse=self.live)
            # Frames in flight when the router died are lost with it: send them again as soon as
            # the consumers are reachable, instead of waiting for `resend_after` (issue 7).
            self._entities.append(self.publisher("camera/frame").declare_matching_listener(self._on_matching))

    def _listen_to_ros2(self) -> None:
        """A ros2: source: subscribe to its topics as the node `source` of the ROS 2 graph (graph.py)."""
        from services.ros2wire.graph import RosNode
        from services.ros2wire.messages import RosMessages
        from services.ros2wire.rmw_zenoh import RELIABLE_QOS, SENSOR_QOS, WireError, normalise_namespace, parse_attachment

        p = self.graph
        ros = RosMessages(p.ros_distro)
        self.ros_node = RosNode(self.session, "source", normalise_namespace(p.ros_namespace), p.ros_domain_id,
                                p.ros_distro, p.ros2_keys, hashes=ros.rihs01)
        rmw_keys = p.ros2_keys == "rmw_zenoh"
        for role, topic, types in self.frames.subscriptions():
            def on_sample(key, msgtype, cdr, attachment, role=role):
                attached = None
                if rmw_keys:
                    try:
                        parse_attachment(attachment)
                        attached = True
                    except WireError:
                        attached = False
                self.frames.on_sample(role, key, msgtype, cdr, attached)

            self.ros_node.subscription(topic, types, SENSOR_QOS if role in ("image", "right") else RELIABLE_QOS, on_sample)
        self.frames.bind(self._stop)
        log.info("source: listening to %s (ROS domain %d, %s keys)", ", ".join(self.frames.topics.values()),
                 p.ros_domain_id, p.ros2_keys)

    def teardown(self) -> None:
        if self.ros_node is not None:
            self.ros_node.close()

    def _on_matching(self, status) -> None:   # a Zenoh thread
        self.replay.subscribers(status.matching, time.monotonic())

    def on_ack(self, message: Message) -> None:
        before = self.limit
        self.replay.acked(message.header.seq, time.monotonic())
        if self.flow is not None:
            if self.flow.limit != before and not self.flow.probing:
                log.debug("source: window %d (%.1f frames/s, %.0f ms without a queue)", self.flow.limit,
                          self.flow.rate or 0.0, 1e3 * (self.flow.min_latency or 0.0))

    @property
    def limit(self) -> int:
        """Frames in flight before the source waits (0: no flow control)."""
        return self.replay.limit

    def on_idle(self) -> None:
        resend = self.replay.resend_due(time.monotonic())
        if resend is not None:
            self._resend(resend)
        if self.finished:
            if self.replay.settled:
                self.completed = True   # every frame out (and acknowledged): the run is over
                if self.config.exit_at_end:
                    log.info("source: all %d frames sent%s", self.sent, " and acknowledged" if self.window else "")
                    self.stop()
            self._pause()
            return
        if self.replay.full:
            waited = self.replay.stalled(time.monotonic())
            if waited is not None:
                log.warning("source: waited %.0f s for %s of frame %d", waited, self.config.ack_topic, self.replay.oldest)
            self._read_ahead()
            self._pause()
            return
        self.replay.moving()
        delay = self.pacer.delay(time.monotonic())
        if delay > 0:
            self._pause(min(delay, 0.05))
            return
        if self.sent == 0 and not (self._pipeline_ready() and self._subscribers_ready()):
            self._pause(0.05)
            return
        if self.sent == 0 and self.config.resume and not self.resume_checked:
            self._resume()
        message, self.ready = self.ready or self._read(), None
        if message is None:
            self.finished = True
            return
        seq = message.header.seq
        self.publish("camera/frame", message)
        self.last_seq = seq
        self.replay.sent(seq, message, time.monotonic())

    def _read(self) -> CameraFrame | None:
        """The next frame's message (None after the last)."""
        frame = self.feed.next()
        if frame is None:
            return None
        # A replay taking every step-th frame numbers them as its source does: step apart, no gap.
        header = self.header(frame.seq, frame.stamp, "camera").model_copy(update={"stride": 1 if self.live else self.config.step})
        return frame_message(frame, header)

    def _read_ahead(self) -> None:
        """While the window is full, read (decode, render) the next frame of a replay, so that it
        goes out as soon as the window opens: reading is then no stage of its own that the frames
        in flight wait for. Not a live camera (its newest frame is taken when it can go out), nor
        before the first frame (where a resume may start elsewhere)."""
        if self.ready is None and self.sent and not self.live and not self.finished:
            self.ready = self._read()
            self.finished = self.ready is None

    def _resume(self) -> None:
        """Start at the last frame every running service has handled (module docstring)."""
        self.resume_checked = True
        handled = {status.header.seq for status in statuses(self.session, self.robot, timeout=RESUME_QUERY_S)
                   if status.service != self.name and status.received > 0}
        if not handled:
            log.info("source: no running service has handled a frame; starting at the first")
            return
        seq = min(handled)
        if not self.feed.can_resume:
            log.warning("source: the running services have handled frame %d, but this source cannot start mid-run; "
                        "starting at its first frame", seq)
            return
        index = self.feed.resume_at(seq)
        log.info("source: the running services have all handled frame %d; resuming there (lap %d, frame %d of %d)",
                 seq, self.laps + 1, index, len(self.frames))

    def _resend(self, resend: Resend) -> None:
        if self.live:   # old frames of a live camera are worth nothing: make room for the newest
            log.warning("source: %s; giving up the %d frames in flight (live camera)", resend.reason, resend.abandoned)
            return
        log.warning("source: %s; sending the %d frames in flight again (from %d)", resend.reason, resend.in_flight,
                    resend.first)
        for message in resend.frames:
            self.publish("camera/frame", message)
        self.replay.resend_done(time.monotonic())

    def extra_counters(self) -> dict[str, float]:
        extra = {"frames_sent": self.sent, "in_flight": len(self.replay.in_flight), "frames_resent": self.resent,
                 "frames_unreadable": len(getattr(self.frames, "unreadable", ()))}
        if self.completed:   # observers (the viewer) show the run as finished
            extra["finished"] = 1
        if self.flow is not None:
            extra["window"] = self.flow.limit
            if self.flow.rate is not None and self.flow.min_latency is not None:
                extra["window_rate_fps"] = round(self.flow.rate, 2)
                extra["window_min_latency_ms"] = round(1e3 * self.flow.min_latency, 1)
        if self.live:
            extra["frames_dropped"] = getattr(self.frames, "frames_dropped", 0)
            extra["frames_abandoned"] = self.replay.abandoned
        for kind, count in getattr(self.frames, "counters", {}).items():   # a ros2: source's bad input
            extra[f"ros2_{kind}"] = count
        return {**super().extra_counters(), **extra}

    def _pipeline_ready(self) -> bool:
        """Hold the first frame until every service of `wait_for` has its health token on the network."""
        now = time.monotonic()
        if self.pipeline_ready or now - self.pipeline_checked < 0.2:
            return self.pipeline_ready
        self.pipeline_checked = now
        live = {service for _, service, _ in live_services(self.session, self.robot, timeout=1.0)}
        missing = sorted(set(self.config.wait_for) - live)
        if not missing:
            log.info("source: %s on the network; sending", ", ".join(self.config.wait_for))
            self.pipeline_ready = True
        elif not self.pipeline_wait_said:
            log.info("source: waiting for %s to come up", ", ".join(missing))
            self.pipeline_wait_said = True
        return self.pipeline_ready

    def _subscribers_ready(self) -> bool:
        """Hold the first frame until someone subscribes to camera/frame (none is lost at start)."""
        return self.publisher("camera/frame").matching_status.matching

    def _pause(self, seconds: float = 0.002) -> None:
        self._stop.wait(seconds)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", help="kitti:PATH, stereo:PATH, images:PATH, video:FILE, camera:N, synthetic:SEED, "
                                         "rosbag:PATH or ros2:TOPIC")
    parser.add_argument("--preset", help="source preset: nubot, kitti, stlucia, synthetic, campus, irat, or a preset file")
    add_field_flag(parser, SourceConfig, "calibration", metavar="FILE")
    add_fov_argument(parser)
    for name in ("mono", "start", "origin", "stop"):
        add_field_flag(parser, SourceConfig, name)
    add_field_flag(parser, SourceConfig, "step", flag="--stride", metavar="N")
    add_renamed_flag(parser, "--step", "--stride", dest="step", type=int)
    add_field_flag(parser, SourceConfig, "rate", metavar="HZ")
    add_field_flag(parser, SourceConfig, "window", metavar="N")
    parser.add_argument("--adaptive-window", action=argparse.BooleanOptionalAction, default=None,
                        help=f"{SourceConfig.model_fields['adaptive_window'].description.rstrip('.')} (default on)")
    add_field_flag(parser, SourceConfig, "live_window", metavar="N")
    add_field_flag(parser, SourceConfig, "ack_topic", metavar="TOPIC")
    add_field_flag(parser, SourceConfig, "resend_after", metavar="S")
    add_field_flag(parser, SourceConfig, "resend_acknowledged", metavar="N")
    add_field_flag(parser, SourceConfig, "loop")
    parser.add_argument("--wait-for", type=lambda text: [name.strip() for name in text.split(",") if name.strip()],
                        help="services whose health tokens must be up before the first frame, comma separated")
    add_field_flag(parser, SourceConfig, "resume")
    add_world_arguments(parser)
    add_bag_arguments(parser)
    from services.ros2wire.graph_settings import add_graph_arguments

    add_graph_arguments(parser)


def add_fov_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--fov", type=float, metavar="DEG", help=_SourceSettings.model_fields["fov"].description)


def config_from_args(args: argparse.Namespace) -> SourceConfig:
    """The service's configuration: the config file's [source] < GRIDSLAM_SOURCE_* < flags
    (world settings from --laps and --world KEY=VALUE, a ROS bag's topics from --image-topic ...)."""
    fields = ("source", "preset", "calibration", "fov", "mono", "start", "origin", "stop", "step", "rate", "window", "adaptive_window",
              "live_window", "ack_topic", "resend_after", "resend_acknowledged", "loop", "wait_for", "resume", *BAG_KEYS)
    return load_config(SourceConfig, "source", config_file=args.config,
                       overrides={**{name: getattr(args, name) for name in fields}, **parse_world_flags(args.world, args.laps)})


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    config = config_from_args(args)
    frames = open_source(config.source, start=config.start, stop=config.stop, step=config.step, preset=config.preset,
                         calibration=config.calibration, mono=config.mono, origin=config.origin, world=config.world(),
                         topics=bag_settings(config), fov=config.fov)
    graph = None
    if config.source.startswith("ros2:"):
        from services.ros2wire.graph_settings import GraphConfig, graph_flags, graph_params, load_graph_config

        graph = graph_params(load_graph_config(GraphConfig, graph_flags(args), args.config))
    return SourceService(runtime, config, frames, args.instance, graph=graph).run()
