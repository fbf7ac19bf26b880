"""A picture of what a run.mcap holds, decoded from the file itself (no Foxglove needed): the
Odometry track of every stage, the last MarkerArray of the experience map, and the camera image
and grid-cell activity at one moment of the run.

    python -m services.ros.preview RUN.mcap OUT.png [--at SECONDS]

Decoding uses rosbags' CDR deserialiser on the MCAP records read with the `mcap` library.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from services.common.settings import CommandParser
from services.evaluation import plots
from services.ros2wire.messages import ACTIVITY_TOPIC, CAMERA_TOPIC, MARKERS_TOPIC, STAGES, typestore

STYLE = {"groundtruth": ("k", "--", "ground truth"), "egomotion": ("#9a9fa6", "-", "ego-motion"),
         "gridcells": ("#1f6fd1", "-", "grid cells"), "map": ("#1a9a4b", "-", "map")}


def read(path: Path) -> dict[str, list[tuple[int, object]]]:
    """{topic: [(log time ns, message)]} of the topics drawn."""
    from mcap.reader import make_reader

    store = typestore()
    wanted = {topic for topic, _ in STAGES.values()} | {MARKERS_TOPIC, CAMERA_TOPIC, ACTIVITY_TOPIC}
    messages: dict[str, list] = {}
    with open(path, "rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages(topics=sorted(wanted)):
            messages.setdefault(channel.topic, []).append((message.log_time, store.deserialize_cdr(message.data, schema.name)))
    return messages


def nearest(items: list[tuple[int, object]], at: int):
    return min(items, key=lambda item: abs(item[0] - at))[1] if items else None


def preview(path: Path, out: Path, at: float | None = None) -> Path | None:
    messages = read(path)
    figure = plots.new_figure(figsize=(12, 5.2), layout="constrained")
    if figure is None:
        return None
    grid = figure.add_gridspec(2, 3, width_ratios=[2.2, 1, 1])
    ax = figure.add_subplot(grid[:, 0])
    last = max((items[-1][0] for items in messages.values() if items), default=0)
    first = min((items[0][0] for items in messages.values() if items), default=0)
    moment = last if at is None else first + int(at * 1e9)
    markers = [m for t, m in messages.get(MARKERS_TOPIC, []) if t <= moment]
    if markers:
        for marker in markers[-1].markers:
            points = np.array([(p.x, p.y) for p in marker.points]).reshape(-1, 2)
            colour = (marker.color.r, marker.color.g, marker.color.b)
            if marker.type == 7:   # SPHERE_LIST: the experiences
                ax.scatter(points[:, 0], points[:, 1], s=12, color=colour, zorder=3, label="experiences")
            else:                  # LINE_LIST: the links, two points per segment
                for a, b in zip(points[0::2], points[1::2]):
                    ax.plot([a[0], b[0]], [a[1], b[1]], color=colour, alpha=marker.color.a, linewidth=1.2 if marker.ns != "links" else 0.6)
                ax.plot([], [], color=colour, label=marker.ns.replace("_", " "))
    for stage, (topic, _) in STAGES.items():
        track = np.array([(m.pose.pose.position.x, m.pose.pose.position.y) for t, m in messages.get(topic, []) if t <= moment])
        if len(track):
            colour, line, label = STYLE[stage]
            ax.plot(track[:, 0], track[:, 1], line, color=colour, linewidth=1.4, label=f"{topic} ({label})")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=7)
    ax.set_title(f"{path.name}: Odometry of every stage and /gridslam/map/markers at {(moment - first) / 1e9:.1f} s", fontsize=9)
    camera = nearest(messages.get(CAMERA_TOPIC, []), moment)
    if camera is not None:
        image = cv2.imdecode(np.asarray(camera.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        axis = figure.add_subplot(grid[0, 1:])
        axis.imshow(image[..., ::-1])
        axis.set_title(f"{CAMERA_TOPIC} (sensor_msgs/CompressedImage)", fontsize=9)
        axis.axis("off")
    activity = nearest(messages.get(ACTIVITY_TOPIC, []), moment)
    if activity is not None:
        axis = figure.add_subplot(grid[1, 1])
        axis.imshow(np.asarray(activity.data, dtype=np.uint8).reshape(activity.height, activity.width), cmap="viridis")
        axis.set_title(f"{ACTIVITY_TOPIC} (sensor_msgs/Image)", fontsize=9)
        axis.axis("off")
    return plots.save(figure, out)


def main() -> None:
    parser = CommandParser(description=__doc__.splitlines()[0])
    parser.add_argument("mcap", type=Path, help="a run.mcap")
    parser.add_argument("out", type=Path, help="the PNG to write")
    parser.add_argument("--at", type=float, help="seconds into the run to draw (default: the end)")
    args = parser.parse_args()
    written = preview(args.mcap, args.out, args.at)
    print(f"wrote {written}" if written else "matplotlib is not installed: nothing written")


if __name__ == "__main__":
    main()
