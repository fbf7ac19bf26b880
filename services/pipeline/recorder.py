"""Records what a running pipeline publishes, from the outside, like any client would: poses of
every stage, view templates, loop closures, lattice snapshots, and the arrival time of each
frame's message on each topic (for per-stage latency)."""

from __future__ import annotations

import logging
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
import zenoh

from schemas import ServiceStatus
from services.common import codec, health, topics
from services.common.convert import heading_of, image_from_msg, pose_to_matrix
from services.common.observe import map_items
from services.common.runtime import RuntimeConfig, open_session
from services.ros2wire.messages import camera_jpeg

log = logging.getLogger(__name__)

RECORDED_TOPICS = ("camera/frame", "egomotion", "grid/pose", "grid/activity", "view/template", "loop/closure", "map/pose",
                   "map/update")


@dataclass
class Recording:
    """Everything recorded, keyed by frame seq. Arrival times are this host's monotonic clock."""

    stamps: dict[int, float] = field(default_factory=dict)
    ground_truth: dict[int, np.ndarray] = field(default_factory=dict)
    increments: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    grid_poses: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    map_poses: dict[int, tuple[float, float, float, int, bool]] = field(default_factory=dict)   # x, y, heading, experience, localized
    final_map: dict[int, tuple[float, float, float]] = field(default_factory=dict)   # frames on the final map
    map_decisions: list[tuple[int, int, str]] = field(default_factory=list)   # the final map's closures: frame, matched, fate
    # A session on a saved map: the first frame number of this run's frames in the map
    # (services/common/layout.py; closures and decisions name frames so), and the true positions
    # of the saved sessions' frames (from their results folder), to judge closures to them.
    frame_base: int = 0
    saved_truth: dict[int, tuple[float, float]] = field(default_factory=dict)
    whole_map: dict[int, tuple[float, float, float]] = field(default_factory=dict)   # every session's frames, final map
    templates: dict[int, tuple[int, bool]] = field(default_factory=dict)
    closures: dict[int, tuple[int, int, int, int]] = field(default_factory=dict)   # frame → closure (once, if re-sent)
    lattices: dict[int, np.ndarray] = field(default_factory=dict)
    # For run.mcap (services/ros): the left camera image as JPEG (at most CAMERA_MAX_WIDTH wide),
    # the intrinsics of that JPEG (fx, fy, cx, cy, width, height), and the experience map's
    # changes: (seq, experiences created or moved [(id, x, y)], links created [(source, target, kind)]).
    camera_jpegs: dict[int, bytes] = field(default_factory=dict)
    camera_model: tuple[float, float, float, float, int, int] | None = None
    map_updates: list[tuple[int, list, list]] = field(default_factory=list)
    camera_jpeg_s: float = 0.0   # time spent encoding them
    arrivals: dict[str, dict[int, float]] = field(default_factory=lambda: defaultdict(dict))
    decode_errors: int = 0


class Recorder:
    """Subscribes to every pipeline topic of one robot and fills a Recording."""

    def __init__(self, runtime: RuntimeConfig, camera_images: bool = True):
        self.runtime = runtime
        self.camera_images = camera_images   # keep each frame's left image as JPEG (for run.mcap)
        self.recording = Recording()
        self.lock = threading.Lock()
        self.session: zenoh.Session | None = None
        self._subscribers = []
        self._last_status: dict[tuple[str, str], ServiceStatus] = {}   # (service, instance) → last published

    def __enter__(self) -> Recorder:
        self.session = open_session(self.runtime)
        for topic in RECORDED_TOPICS:
            self._subscribers.append(self.session.declare_subscriber(
                topics.key(self.runtime.robot, topic), lambda sample, topic=topic: self._on_sample(topic, sample)))
        self._subscribers.append(self.session.declare_subscriber(topics.key(self.runtime.robot, "status/*/*"), self._on_status))
        return self

    def __exit__(self, *exc) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers.clear()
        if self.session is not None:
            self.session.close()
            self.session = None

    def count(self, topic: str) -> int:
        with self.lock:
            return len(self.recording.arrivals[topic])

    def last_seq(self, topic: str) -> int | None:
        with self.lock:
            seqs = self.recording.arrivals[topic]
            return max(seqs) if seqs else None

    def live_instances(self) -> set[str]:
        """Instance names of the services of this robot whose health token is alive."""
        return {instance for _, _, instance in health.live_services(self.session, self.runtime.robot)}

    def statuses(self) -> dict[str, dict]:
        """The status counters of every service of this robot, by service name (by instance name
        for a second instance of a service, e.g. egomotion-2): as the live ones answer now, and
        as those that already ended (the source) last published them."""
        with self.lock:
            found = dict(self._last_status)
        found.update({(status.service, status.instance): status
                      for status in health.statuses(self.session, self.runtime.robot, timeout=3)})
        return {service if instance == service else instance: status.model_dump(exclude={"header", "schema_version"})
                for (service, instance), status in found.items()}

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            status = codec.decode(sample.payload.to_bytes(), ServiceStatus, str(sample.encoding))
        except codec.CodecError:
            return
        with self.lock:
            self._last_status[(status.service, status.instance)] = status

    def _on_sample(self, topic: str, sample: zenoh.Sample) -> None:
        arrival = time.monotonic()
        try:
            message = codec.decode(sample.payload.to_bytes(), topics.model_of(topic), str(sample.encoding))
        except codec.CodecError as error:
            with self.lock:
                self.recording.decode_errors += 1
            log.warning("recorder: dropped message on %s: %s", sample.key_expr, error)
            return
        seq = message.header.seq
        r = self.recording
        jpeg = model = None
        if topic == "camera/frame" and self.camera_images:   # encoded before taking the lock
            started = time.perf_counter()
            jpeg, scale = camera_jpeg(image_from_msg(message.left), message.left.encoding)
            info = message.camera_info
            model = None if info is None else (info.fx * scale, info.fy * scale, info.cx * scale, info.cy * scale,
                                               round(message.left.width * scale), round(message.left.height * scale))
            encoding_s = time.perf_counter() - started
        with self.lock:
            r.arrivals[topic].setdefault(seq, arrival)
            if topic == "camera/frame":
                r.stamps[seq] = message.header.stamp.to_seconds()
                if message.ground_truth is not None:
                    r.ground_truth[seq] = pose_to_matrix(message.ground_truth)
                if jpeg is not None:
                    r.camera_jpegs[seq] = jpeg
                    r.camera_model = model or r.camera_model
                    r.camera_jpeg_s += encoding_s
            elif topic == "egomotion":
                r.increments[seq] = (message.increment.forward, message.increment.left, message.increment.yaw)
            elif topic == "grid/pose":
                r.grid_poses[seq] = (message.pose.position.x, message.pose.position.y, message.heading)
            elif topic == "map/pose":
                r.map_poses[seq] = (message.pose.position.x, message.pose.position.y, heading_of(message.pose),
                                    message.experience_id, message.localized)
            elif topic == "view/template":
                r.templates[seq] = (message.template_id, message.is_new)
            elif topic == "loop/closure":
                r.closures[message.frame] = (message.frame, message.matched_frame, message.matched_template, message.votes)
            elif topic == "grid/activity":
                r.lattices[seq] = image_from_msg(message.image)
            elif topic == "map/update":
                r.map_updates.append((seq, *map_items(message)))
