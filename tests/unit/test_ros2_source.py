"""The live ROS 2 source's core (services/source/ros2.py) fed samples as the source service
hands them over: frames decode as a bag's do, the newest frame wins (drops counted), stereo
pairs match by stamp, odometry gives the frame's motion, and each bad input is counted, logged
once with its key and dropped while good samples still get through."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from tests.extras import require

require("rosbags", "ros")

from services.ros2wire.messages import RosMessages   # noqa: E402
from services.source.ros2 import Ros2Source   # noqa: E402

KEY = "0/cam/image_raw/sensor_msgs::msg::dds_::Image_/H"
ros = RosMessages("jazzy")


def image(stamp_ns: int, pixels: np.ndarray, step: int | None = None) -> bytes:
    """An Image message; a `step` below the width is an image whose data does not fit its size."""
    height, width = pixels.shape
    step = width if step is None else step
    data = np.ascontiguousarray(pixels[:, :step]).reshape(-1)
    message = ros.types["sensor_msgs/msg/Image"](header=ros._header(stamp_ns, "camera"), height=height, width=width,
                                                 encoding="mono8", is_bigendian=0, step=step, data=data)
    return ros._serialize(message, "sensor_msgs/msg/Image")


def pixels(value: int) -> np.ndarray:
    return (np.arange(6 * 8).reshape(6, 8) + value).astype(np.uint8)


def test_frames_decode_and_the_newest_wins():
    source = Ros2Source("/cam/image_raw", fov=90.0)
    for seq in range(3):
        source.on_sample("image", KEY, "sensor_msgs/msg/Image", image(10**9 + seq * 10**8, pixels(seq)), True)
    frame = source.latest(0.1)
    assert frame.seq == 2 and frame.stamp == pytest.approx(1.2) and np.array_equal(frame.left, pixels(2))
    assert source.frames_dropped == 2   # frames 0 and 1, replaced before they were taken
    assert source.camera_assumed and source.camera.width == 8 and source.camera.fx == pytest.approx(4.0)
    assert source.latest(0.01) is None


def test_stereo_pairs_match_by_stamp_and_odometry_moves_the_frame():
    source = Ros2Source("/left", right_image_topic="/right", odom_topic="/odom", stereo_tolerance=0.005, fov=90.0)
    for stamp, x in ((0, 0.0), (10**9, 1.0)):
        odometry = ros.odometry(stamp, "odom", "base_link", (x, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
        source.on_sample("odom", "0/odom/nav_msgs::msg::dds_::Odometry_/H", "nav_msgs/msg/Odometry", odometry, True)
    source.on_sample("image", KEY, "sensor_msgs/msg/Image", image(0, pixels(0)), True)
    assert source.latest(0.01) is None                       # no right image yet
    source.on_sample("right", KEY, "sensor_msgs/msg/Image", image(2_000_000, pixels(9)), True)
    first = source.latest(0.1)
    assert first.seq == 0 and np.array_equal(first.right, pixels(9)) and first.odometry == (0.0, 0.0, 0.0)
    source.on_sample("image", KEY, "sensor_msgs/msg/Image", image(5 * 10**8, pixels(1)), True)
    source.on_sample("right", KEY, "sensor_msgs/msg/Image", image(5 * 10**8 + 20_000_000, pixels(1)), True)  # 20 ms: no pair
    assert source.latest(0.01) is None
    source.on_sample("right", KEY, "sensor_msgs/msg/Image", image(5 * 10**8 + 1_000_000, pixels(1)), True)
    second = source.latest(0.1)
    assert second.seq == 1 and second.odometry[0] == pytest.approx(0.5) and abs(second.odometry[1]) < 1e-12


def test_each_bad_input_is_counted_logged_once_and_dropped(caplog):
    source = Ros2Source("/cam/image_raw", fov=90.0)
    good = image(0, pixels(0))
    with caplog.at_level(logging.WARNING, logger="services.source.ros2"):
        for _ in range(2):
            source.on_sample("image", KEY, "sensor_msgs/msg/Image", good[:20], True)             # cut short: malformed
            source.on_sample("image", KEY, "sensor_msgs/msg/Image", b"\x07" * 64, True)           # not CDR
            source.on_sample("image", KEY, "std_msgs/msg/String", ros.closure(0, {})[1], True)    # another type
            source.on_sample("image", KEY, "sensor_msgs/msg/Image", good, False)                  # no attachment
        source.on_sample("image", KEY, "sensor_msgs/msg/Image", image(1, pixels(1), step=4), True)  # step < width
        assert source.latest(0.05) is None
        source.on_sample("image", KEY, "sensor_msgs/msg/Image", image(2, pixels(2)), True)
        frame = source.latest(0.1)
    assert np.array_equal(frame.left, pixels(2))   # the good sample after them still gets through
    assert source.counters == {"malformed": 4, "unexpected_type": 2, "no_attachment": 2, "bad_image": 1}
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 4 and all(KEY in w for w in warnings)   # once per key and kind
    assert any("unexpected_type" in w and "std_msgs/msg/String" in w for w in warnings)


def test_frames_wait_for_their_camera_info():
    source = Ros2Source("/cam/image_raw", camera_info_topic="/cam/camera_info")
    source.on_sample("image", KEY, "sensor_msgs/msg/Image", image(0, pixels(0)), True)
    assert source.latest(0.05) is None and source.frames_waiting == 1
    _, info = ros.camera_info(0, 500.0, 501.0, 4.0, 3.0, 8, 6)
    source.on_sample("camera_info", "0/cam/camera_info/x/H", "sensor_msgs/msg/CameraInfo", info, True)
    source.on_sample("image", KEY, "sensor_msgs/msg/Image", image(1, pixels(1)), True)
    frame = source.latest(0.1)
    assert (frame.camera.fx, frame.camera.fy, frame.camera.cx, frame.camera.cy) == (500.0, 501.0, 4.0, 3.0)
    assert not source.camera_assumed
