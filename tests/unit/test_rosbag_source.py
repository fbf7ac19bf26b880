"""The ROS bag source: bags written here with `rosbags` from the synthetic world's frames, in
every storage (ROS 1, ROS 2 sqlite3, ROS 2 MCAP), mono and stereo, raw and compressed, read
back and compared with the frames they were made from; and every bad input as one line."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from tests.extras import require

require("rosbags", "ros")

from services.common.errors import GridslamError   # noqa: E402
from services.source import Camera, SourceError, open_source   # noqa: E402
from services.source.rosbag import decode_image, interpolate_planar   # noqa: E402
from tests.bags import FORMATS, LEFT, ODOM, image_topic, write_bag   # noqa: E402

FRAMES = 8
# JPEG at OpenCV's default quality 95 of the synthetic grey frames: the largest pixel change
# seen was 10 grey levels, the mean about 1 (measured here); bounds with a margin.
JPEG_MAX_ERROR, JPEG_MEAN_ERROR = 16, 2.0


@pytest.fixture(scope="module")
def frames():
    with open_source("synthetic:0", preset="synthetic", stop=FRAMES) as source:
        return list(source)


def bag_path(tmp_path, fmt: str, name: str = "run"):
    return tmp_path / (f"{name}.bag" if fmt == "ros1" else name)


def topics(stereo: bool, compression: str | None) -> dict:
    settings = {"image_topic": image_topic(compression=compression), "odom_topic": ODOM}
    if stereo:
        settings["right_image_topic"] = image_topic(compression=compression, side="right")
    return settings


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("stereo", [True, False], ids=["stereo", "mono"])
@pytest.mark.parametrize("compression", [None, "png", "jpeg"], ids=["raw", "png", "jpeg"])
def test_bag_frames_equal_the_frames_they_were_written_from(tmp_path, frames, fmt, stereo, compression):
    path = write_bag(bag_path(tmp_path, fmt), frames, fmt=fmt, stereo=stereo, compression=compression)
    source = open_source(f"rosbag:{path}", topics=topics(stereo, compression))
    read = list(source)
    assert len(source) == len(read) == FRAMES and [f.seq for f in read] == list(range(FRAMES))
    # Intrinsics and the stereo baseline come from the bag's CameraInfo (P, and the right P's −fx·b).
    assert source.camera == (frames[0].camera if stereo else Camera(**{**frames[0].camera.__dict__, "baseline": 0.0}))
    for got, made in zip(read, frames):
        assert got.stamp == made.stamp
        images = [(got.left, made.left)] + ([(got.right, made.right)] if stereo else [])
        assert (got.right is None) is (not stereo)
        for image, original in images:
            assert image.shape == original.shape and image.dtype == np.uint8
            error = np.abs(image.astype(int) - original)
            if compression == "jpeg":
                assert error.max() <= JPEG_MAX_ERROR and error.mean() <= JPEG_MEAN_ERROR
            else:
                assert error.max() == 0   # lossless: the very pixels
        # Ground truth and odometry from nav_msgs/Odometry at the image stamps.
        np.testing.assert_allclose(got.ground_truth, made.ground_truth, atol=1e-12)
        np.testing.assert_allclose(got.odometry, made.odometry, atol=1e-12)
    # Indexed access reads one frame through the bag's index: the same as iteration.
    assert np.array_equal(source[5].left, read[5].left) and source[5].stamp == read[5].stamp
    source.close()


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono16"])
def test_colour_and_16_bit_encodings_read_as_the_grey_frames(tmp_path, frames, encoding):
    path = write_bag(bag_path(tmp_path, "mcap"), frames, stereo=False, encoding=encoding)
    colour = open_source(f"rosbag:{path}", topics=topics(False, None))[3]
    expected = frames[3].left if encoding == "mono16" else cv2.cvtColor(frames[3].left, cv2.COLOR_GRAY2BGR)
    assert np.array_equal(colour.left, expected)   # rgb8 comes out as BGR like every source's colour
    preset = tmp_path / "grey.toml"
    preset.write_text("grey = true\n")
    grey = open_source(f"rosbag:{path}", preset=str(preset), topics=topics(False, None))[3]
    assert np.array_equal(grey.left, frames[3].left)


def test_the_only_image_topic_is_taken_without_a_flag_and_a_calibration_wins_over_camera_info(tmp_path, frames):
    path = write_bag(bag_path(tmp_path, "sqlite3"), frames, stereo=False, odometry=False)
    camera = Camera(100.0, 100.0, 160.0, 120.0)
    source = open_source(f"rosbag:{path}", calibration=camera)
    assert source.camera == Camera(100.0, 100.0, 160.0, 120.0, 0.0, 320, 240)
    frame = source[0]
    assert frame.ground_truth is None and frame.odometry is None   # no odometry topic given
    assert np.array_equal(frame.left, frames[0].left)


def test_stereo_pairs_are_matched_by_stamp_and_a_lone_left_image_leaves_a_gap(tmp_path, frames, caplog):
    # Frame 3's right image is 20 ms late (beyond the 5 ms default), frame 5's 2 ms (within).
    path = write_bag(bag_path(tmp_path, "mcap"), frames, stereo=True, right_delays={3: 0.02, 5: 0.002})
    with caplog.at_level(logging.WARNING, logger="services.source.rosbag"):
        source = open_source(f"rosbag:{path}", topics=topics(True, None))
    assert source.seqs == (0, 1, 2, 4, 5, 6, 7)
    assert "1 of 8 images" in caplog.text
    assert np.array_equal(source[source.seqs.index(5)].right, frames[5].right)
    wide = open_source(f"rosbag:{path}", topics={**topics(True, None), "stereo_tolerance": 0.05})
    assert len(wide) == FRAMES


def test_frames_outside_the_odometry_are_without_ground_truth():
    times = np.array([1.0, 2.0, 3.0])
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [2.0, 1.0, 1.0]])
    assert interpolate_planar(times, poses, 0.5) is None and interpolate_planar(times, poses, 3.5) is None
    assert interpolate_planar(times, poses, 2.0) == (1.0, 0.0, 0.5)
    assert interpolate_planar(times, poses, 2.5) == pytest.approx((1.5, 0.5, 0.75))


def test_presets_name_openratslams_topics(tmp_path, frames):
    from services.source.spec import load_preset

    assert load_preset("irat")[1] == {"image_topic": "/irat_red/camera/image/compressed", "odom_topic": "/irat_red/odom",
                                      "grey": True}
    assert load_preset("stlucia")[1]["image_topic"] == "/stlucia/camera/image/compressed"
    # A bag laid out as the iRat's opens with the preset alone.
    path = write_bag(bag_path(tmp_path, "ros1", "irat"), frames, fmt="ros1", stereo=False, compression="jpeg",
                     left_topic="/irat_red/camera/image", odom_topic="/irat_red/odom", camera_info=False)
    source = open_source(f"rosbag:{path}", preset="irat")
    assert len(source) == FRAMES and source.camera is None and source[2].odometry is not None


# ------------------------------------------------------------------------- bad input, one line each
def test_a_missing_topic_names_it_and_lists_the_bags_image_topics(tmp_path, frames):
    path = write_bag(bag_path(tmp_path, "mcap"), frames[:2], stereo=True)
    with pytest.raises(SourceError, match=r"no topic /camera/left .*image topics: /stereo/left/image_raw, /stereo/right/image_raw"):
        open_source(f"rosbag:{path}", topics={"image_topic": "/camera/left"})
    with pytest.raises(SourceError, match=r"choose the camera with --image-topic"):
        open_source(f"rosbag:{path}")
    with pytest.raises(SourceError, match=r"topic /robot/odom is nav_msgs/msg/Odometry, expected sensor_msgs/msg/Image"):
        open_source(f"rosbag:{path}", topics={"image_topic": ODOM})
    with pytest.raises(SourceError, match=r"no topic /odom \(Odometry topics: /robot/odom\)"):
        open_source(f"rosbag:{path}", topics={"image_topic": LEFT, "odom_topic": "/odom"})
    with pytest.raises(SourceError, match="ROS bag not found"):
        open_source(f"rosbag:{tmp_path / 'absent.bag'}")


def test_an_unknown_encoding_names_the_topic_and_the_encoding(tmp_path, frames):
    path = write_bag(bag_path(tmp_path, "sqlite3"), frames[:2], stereo=False, encoding="yuv422")
    with pytest.raises(SourceError, match=rf"topic {LEFT}: image encoding 'yuv422' is not supported"):
        open_source(f"rosbag:{path}")


def test_a_truncated_bag_names_the_byte_where_it_ends(tmp_path, frames):
    ros1 = write_bag(bag_path(tmp_path, "ros1"), frames[:4], fmt="ros1", stereo=False)
    size = ros1.stat().st_size
    with ros1.open("r+b") as stream:
        stream.truncate(size // 2)
    with pytest.raises(SourceError, match=rf"{ros1.name}: the index should start at byte \d+ but the file ends at byte {size // 2}"):
        open_source(f"rosbag:{ros1}")
    folder = write_bag(bag_path(tmp_path, "mcap", "ros2"), frames[:4], stereo=False)
    mcap = next(folder.glob("*.mcap"))
    size = mcap.stat().st_size
    with mcap.open("r+b") as stream:
        stream.truncate(size - 100)
    with pytest.raises(SourceError, match=rf"{mcap.name}: the file ends at byte {size - 100} without MCAP's closing magic"):
        open_source(f"rosbag:{folder}")
    garbage = tmp_path / "garbage.bag"
    garbage.write_bytes(b"not a bag at all" * 10)
    with pytest.raises(GridslamError, match="garbage.bag"):
        open_source(f"rosbag:{garbage}")


def test_decode_image_rejects_what_it_cannot_read():
    class Compressed:
        format = "compressedDepth png"
        data = np.zeros(4, np.uint8)

    with pytest.raises(SourceError, match=r"topic /depth: compressed image format 'compressedDepth png' is not supported"):
        decode_image(Compressed(), "sensor_msgs/msg/CompressedImage", "/depth", grey=False)
    Compressed.format, Compressed.data = "jpeg", np.frombuffer(b"\xff\xd8 broken", np.uint8)
    with pytest.raises(SourceError, match="does not decode"):
        decode_image(Compressed(), "sensor_msgs/msg/CompressedImage", "/cam", grey=False)


def test_a_source_without_the_extra_says_how_to_install_it(monkeypatch, tmp_path):
    import builtins

    real_import = builtins.__import__

    def no_rosbags(name, *args, **kwargs):
        if name.startswith("rosbags"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    (tmp_path / "x.bag").write_bytes(b"")
    monkeypatch.setattr(builtins, "__import__", no_rosbags)
    with pytest.raises(SourceError, match=r"pip install 'gridslam\[ros\]'"):
        open_source(f"rosbag:{tmp_path / 'x.bag'}")
