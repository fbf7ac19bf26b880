"""`run.mcap`: a whole run as one MCAP file of ROS 2 messages (CDR), which Foxglove opens and
`ros2 bag play` replays. Written by `gridslam run` and `demo` at the end of a run from what the
runner recorded (`content_from_recording`), and again by `gridslam export mcap RESULTS_DIR`
from a results folder (services/pipeline/results_mcap.py). Every message is stamped (header and MCAP log
time) with its frame's source stamp; messages are written in stamp order.

The topics and frames are those of messages.py. The experience map is a MarkerArray written
when the map changed, at most once per MARKER_PERIOD_S seconds of the run's time, and once
more with the final map.
"""

from __future__ import annotations

import heapq
import logging
import time
from dataclasses import dataclass, field
from itertools import count
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from services.evaluation.trajectory import Trajectory
from services.ros2wire.messages import (
    ROUTE_TOPIC, TOPICS, MapState, RosMessages, RosUnavailable, stamp_ns,
)

log = logging.getLogger(__name__)

MCAP_NAME = "run.mcap"
MARKER_PERIOD_S = 1.0
# Stage of messages.STAGES → the stem of its TUM file in a results folder (report.py):
# /gridslam/map is the pose expmap published at each frame.
STAGE_FILES = {"egomotion": "egomotion", "gridcells": "gridcells", "map": "map_online", "groundtruth": "groundtruth"}
CHUNK_BYTES = 4 * 1024 * 1024
# The MCAP ros2 profile's channel metadata `offered_qos_profiles`, as rosbag2 writes it (YAML,
# rmw's enums: history 3 unknown, reliability 1 reliable, durability 1 transient_local or 2
# volatile, liveliness 1 automatic, infinite durations): without it `ros2 bag play` offers every
# topic as volatile, and a static-transform listener never gets /tf_static.
LATCHED_TOPICS = ("/tf_static",)
_INFINITE = "{sec: 2147483647, nsec: 4294967295}"


def offered_qos_profiles(topic: str) -> str:
    """The YAML of one channel's offered QoS profile (a list of one)."""
    durability = 1 if topic in LATCHED_TOPICS else 2
    return (f"- history: 3\n  depth: 0\n  reliability: 1\n  durability: {durability}\n  deadline: {_INFINITE}\n"
            f"  lifespan: {_INFINITE}\n  liveliness: 1\n  liveliness_lease_duration: {_INFINITE}\n"
            "  avoid_ros_namespace_conventions: false\n")


@dataclass
class RunContent:
    """What run.mcap holds, every item with its source stamp in seconds and in stamp order."""

    trajectories: dict[str, Trajectory]                    # stage of messages.STAGES → poses
    images: Iterable[tuple[float, bytes]] = ()             # left camera image, JPEG
    camera_model: tuple | None = None                      # (fx, fy, cx, cy, width, height) of the JPEGs
    lattices: Iterable[tuple[float, np.ndarray]] = ()      # grid-cell activity, uint8
    map_updates: Iterable[tuple[float, list, list]] = ()   # (experiences [(id, x, y)], links [(source, target, kind)])
    closures: list[tuple[float, dict]] = field(default_factory=list)
    metadata: dict[str, str] = field(default_factory=dict)


def content_from_recording(recording, trajectories: dict[str, Trajectory], metadata: dict[str, str] | None = None) -> RunContent:
    """The content of a run from the runner's Recording (services/pipeline/recorder.py) and the
    trajectories evaluated from it (report.trajectories)."""
    stamps = recording.stamps

    def stamped(items: dict):
        return [(stamps[seq], items[seq]) for seq in sorted(items) if seq in stamps]

    return RunContent(
        trajectories={stage: trajectories[name] for stage, name in STAGE_FILES.items() if name in trajectories},
        images=stamped(recording.camera_jpegs),
        camera_model=recording.camera_model,
        lattices=stamped(recording.lattices),
        map_updates=[(stamps[seq], experiences, links) for seq, experiences, links in recording.map_updates if seq in stamps],
        closures=[(stamps[frame], {"frame": frame, "matched_frame": matched, "matched_template": template, "votes": votes})
                  for frame, matched, template, votes in recording.closures.values() if frame in stamps],
        metadata=metadata or {},
    )


def write_after_run(folder: Path, recording, trajectories: dict[str, Trajectory], config) -> dict | None:
    """FOLDER/run.mcap at the end of `gridslam run` (runner.py); what it cost, for metrics.json.
    Without the extra `ros`: one warning, no file, None."""
    started = time.perf_counter()
    metadata = {"source": config.source, "robot": config.robot, "preset": config.preset or ""}
    try:
        counts = write_run_mcap(Path(folder) / MCAP_NAME, content_from_recording(recording, trajectories, metadata))
    except RosUnavailable as error:
        log.warning("%s; no %s written", error, MCAP_NAME)
        return None
    return {"file": MCAP_NAME, "bytes": (Path(folder) / MCAP_NAME).stat().st_size, "messages": sum(counts.values()),
            "write_s": time.perf_counter() - started, "camera_jpeg_s": recording.camera_jpeg_s}


def write_run_mcap(path: Path, content: RunContent) -> dict[str, int]:
    """Write `content` as an MCAP file of ROS 2 messages; returns the message count per topic."""
    ros = RosMessages()
    counts = write_mcap(path, ros, _messages(ros, content), content.metadata)
    log.info("wrote %s: %d messages on %d topics", path, sum(counts.values()), len(counts))
    return counts


def write_route_mcap(path: Path, poses) -> dict[str, int]:
    """A route planned on the map as one nav_msgs/Path in the `map` frame, ``poses`` (N, 3)."""
    ros = RosMessages()
    return write_mcap(path, ros, [(0, ROUTE_TOPIC, ros.path(0, "map", [(0, x, y, heading) for x, y, heading in poses]))],
                      {"content": "gridslam route"})


def write_mcap(path: Path, ros: RosMessages, messages, metadata: dict | None = None) -> dict[str, int]:
    """An MCAP file of (stamp ns, topic, CDR bytes) messages in stamp order; the count per topic."""
    try:
        from mcap.writer import CompressionType, Writer
    except ImportError:
        raise RosUnavailable("writing MCAP needs the optional extra 'ros': pip install 'gridslam[ros]'") from None
    counts: dict[str, int] = {}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as stream:
        writer = Writer(stream, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="gridslam")
        channels: dict[str, int] = {}
        schemas: dict[str, int] = {}
        for number, (stamp, topic, data) in enumerate(messages):
            channel = channels.get(topic)
            if channel is None:
                msgtype = TOPICS[topic]
                if msgtype not in schemas:
                    schemas[msgtype] = writer.register_schema(msgtype, "ros2msg", ros.msgdef(msgtype).encode())
                channel = channels[topic] = writer.register_channel(
                    topic, "cdr", schemas[msgtype], metadata={"offered_qos_profiles": offered_qos_profiles(topic)})
            writer.add_message(channel, log_time=stamp, data=data, publish_time=stamp, sequence=number)
            counts[topic] = counts.get(topic, 0) + 1
        if metadata:
            writer.add_metadata("gridslam", {key: str(value) for key, value in metadata.items()})
        writer.finish()
    return counts


def _messages(ros: RosMessages, content: RunContent) -> Iterator[tuple[int, str, bytes]]:
    """Every message of the run, (stamp ns, topic, CDR bytes), in stamp order. Each stream is
    serialised lazily as the merge reaches it, so only one message per stream is in memory."""
    tie = count()   # keeps the merge stable and never compares payloads

    def stream(items):
        for stamp, topic, data in items:
            yield stamp, next(tie), topic, data

    streams = [stream(_poses(ros, content.trajectories)), stream(_images(ros, content))]
    streams.append(stream((stamp_ns(stamp), *ros.activity(stamp_ns(stamp), pixels)) for stamp, pixels in content.lattices))
    streams.append(stream(_markers(ros, content.map_updates)))
    streams.append(stream((stamp_ns(stamp), *ros.closure(stamp_ns(stamp), fields)) for stamp, fields in content.closures))
    first = min((float(t.stamps[0]) for t in content.trajectories.values() if len(t)), default=0.0)
    streams.append(stream([(stamp_ns(first), *ros.static_transforms(stamp_ns(first)))]))
    for stamp, _, topic, data in heapq.merge(*streams):
        yield stamp, topic, data


def _poses(ros: RosMessages, trajectories: dict[str, Trajectory]):
    """Every stage's Odometry at each stamp, and one /tf message per stamp for all of them."""
    at: dict[int, list] = {}
    for stage, trajectory in trajectories.items():
        for stamp, position, orientation in zip(trajectory.stamps, trajectory.positions, trajectory.quaternions):
            at.setdefault(stamp_ns(float(stamp)), []).append((stage, position, orientation))
    for nanoseconds in sorted(at):
        for topic, data in ros.poses(nanoseconds, at[nanoseconds]):
            yield nanoseconds, topic, data


def _images(ros: RosMessages, content: RunContent):
    for stamp, jpeg in content.images:
        nanoseconds = stamp_ns(stamp)
        yield (nanoseconds, *ros.camera_image(nanoseconds, jpeg))
        if content.camera_model is not None:
            yield (nanoseconds, *ros.camera_info(nanoseconds, *content.camera_model))


def _markers(ros: RosMessages, updates: Iterable[tuple[float, list, list]]):
    """The map after its updates: when it changed, at most once per MARKER_PERIOD_S, and at the end."""
    state, last_written, pending = MapState(), None, None
    for stamp, experiences, links in updates:
        if state.apply(experiences, links):
            pending = stamp
        if pending is not None and (last_written is None or stamp - last_written >= MARKER_PERIOD_S):
            yield (stamp_ns(stamp), *ros.markers(stamp_ns(stamp), state))
            last_written, pending = stamp, None
    if pending is not None:
        yield (stamp_ns(pending), *ros.markers(stamp_ns(pending), state))
