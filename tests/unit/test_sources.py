"""Loaders of the source core: real shared data, synthetic files in tmp_path for every
layout, bad input for every source, and the live camera's newest-frame-only logic."""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.common.errors import ConfigError
from services.source import Camera, SourceError, open_source
from services.source.calibration import read_calibration, write_calibration
from services.source.camera import LiveCamera


def write_png(path: Path, image: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)
    return path


def pattern(seq: int, shape=(24, 32)) -> np.ndarray:
    """A small image whose pixels encode ``seq`` (value 10·seq + 5 everywhere)."""
    return np.full(shape, 10 * seq + 5, np.uint8)


# --- real data -------------------------------------------------------------------------


def test_nubot_stereo_folder_with_preset(shared_data):
    source = open_source(f"stereo:{shared_data / 'nubot_scene1'}", preset="nubot")
    assert len(source) == 205
    assert source.camera == Camera(493.86945, 493.86945, 320.33392, 244.18816, 0.11996, 640, 480)
    frame = source[204]
    assert frame.seq == 204 and frame.stamp == pytest.approx(20.4)
    assert frame.left.shape == (480, 640) and frame.right.shape == (480, 640) and frame.left.dtype == np.uint8
    assert not np.array_equal(frame.left, frame.right)
    assert frame.ground_truth is None and frame.odometry is None
    subset = open_source(f"stereo:{shared_data / 'nubot_scene1'}", preset="nubot", start=10, stop=20, step=3, mono=True)
    frames = list(subset)
    assert [f.seq for f in frames] == [10, 13, 16, 19] and frames[0].right is None
    np.testing.assert_array_equal(frames[1].left, source[13].left)


def test_kitti_clip(shared_data):
    clip = shared_data / "kitti06_clip"
    source = open_source(f"kitti:{clip}", preset="kitti")
    assert len(source) == 51
    camera = source.camera
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (707.0912, 707.0912, 601.8873, 183.1104)
    assert camera.baseline == pytest.approx(379.8145 / 707.0912)
    assert (camera.width, camera.height) == (1226, 370)
    poses = np.loadtxt(clip / "poses.txt").reshape(-1, 3, 4)
    last = source[50]
    assert last.left.shape == (370, 1226) and last.right is None and last.stamp == pytest.approx(5.0)
    np.testing.assert_allclose(last.ground_truth[:3, :], poses[50], atol=1e-9)
    assert 55 < np.linalg.norm(last.ground_truth[:3, 3]) < 60
    # Starting mid-clip re-anchors the ground truth to the first selected frame.
    later = open_source(f"kitti:{clip}", start=20, step=10)
    assert [f.seq for f in later] == [20, 30, 40, 50]
    np.testing.assert_allclose(later[0].ground_truth, np.eye(4), atol=1e-12)
    first = np.vstack([poses[20], [0, 0, 0, 1]])
    expected = np.linalg.inv(first) @ np.vstack([poses[40], [0, 0, 0, 1]])
    np.testing.assert_allclose(later[2].ground_truth, expected, atol=1e-9)


# --- synthetic files for each layout ------------------------------------------------------

KITTI_CALIB = "\n".join(
    [
        "P0: 700 0 300 0 0 710 120 0 0 0 1 0",
        "P1: 700 0 300 -378 0 710 120 0 0 0 1 0",
        "P2: 700 0 300 40 0 710 120 0.2 0 0 1 0.003",
        "P3: 700 0 300 -340 0 710 120 0.2 0 0 1 0.003",
        "Tr: 1 0 0 0 0 1 0 0 0 0 1 0",
    ]
)


def make_kitti_root(root: Path, frames: int = 5) -> Path:
    sequence = root / "sequences" / "07"
    for k in range(frames):
        write_png(sequence / "image_0" / f"{k:06d}.png", pattern(k))
        write_png(sequence / "image_1" / f"{k:06d}.png", pattern(k + 1))
    (sequence / "calib.txt").write_text(KITTI_CALIB + "\n")
    (sequence / "times.txt").write_text("".join(f"{0.1037 * k:.6e}\n" for k in range(frames)))
    (root / "poses").mkdir()
    (root / "poses" / "07.txt").write_text("".join(f"1 0 0 {k * 0.5} 0 1 0 0 0 0 1 {k * 2.0}\n" for k in range(frames)))
    return sequence


def test_kitti_official_layout(tmp_path):
    sequence = make_kitti_root(tmp_path)
    for spec in (f"kitti:{tmp_path}", f"kitti:{sequence}"):
        source = open_source(spec)
        assert len(source) == 5
        assert source.camera == Camera(700, 710, 300, 120, 0.54, 32, 24)
        frame = source[3]
        assert frame.stamp == pytest.approx(0.3111)
        assert frame.left[0, 0] == 35 and frame.right[0, 0] == 45
        np.testing.assert_allclose(frame.ground_truth[:3, 3], [1.5, 0, 6.0])
    # Poses inside the sequence folder are found too.
    (tmp_path / "poses").rename(sequence / "poses")
    assert open_source(f"kitti:{sequence}", start=1)[1].ground_truth[2, 3] == pytest.approx(2.0)


def test_image_folder_natural_order(tmp_path):
    for k in (1, 2, 10, 11):
        write_png(tmp_path / f"img{k}.png", pattern(k))
    (tmp_path / "notes.txt").write_text("not an image")
    source = open_source(f"images:{tmp_path}")
    assert [int(f.left[0, 0]) for f in source] == [15, 25, 105, 115]
    assert [f.seq for f in source] == [0, 1, 2, 3] and source[2].stamp == pytest.approx(0.2)
    # No calibration: a pinhole camera is assumed, centred, with the default field of view (65°).
    assert source.camera_assumed and source.camera.fx == pytest.approx(16 / math.tan(math.radians(32.5)))
    assert (source.camera.cx, source.camera.cy, source.camera.baseline) == (15.5, 11.5, 0.0)
    assert source[0].camera == source.camera
    assert open_source(f"images:{tmp_path}", fov=90.0).camera.fx == pytest.approx(16.0)
    calibrated = open_source(f"images:{tmp_path}", calibration=Camera(20.0, 20.0, 16.0, 12.0))
    assert not calibrated.camera_assumed and calibrated.camera.fx == 20.0


def test_video_file_indexed_and_stepped(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (64, 48))
    for k in range(12):
        writer.write(cv2.cvtColor(pattern(k, (48, 64)), cv2.COLOR_GRAY2BGR))
    writer.release()
    source = open_source(f"video:{path}")
    assert len(source) == 12
    assert source.camera_assumed and source.camera.fx == pytest.approx(32 / math.tan(math.radians(32.5)))   # none given
    for k in (7, 2, 11, 0):  # seeking back and forth
        frame = source[k]
        assert frame.seq == k and abs(float(frame.left.mean()) - (10 * k + 5)) < 3
        assert frame.stamp == pytest.approx(k / 15.0)
    stepped = open_source(f"video:{path}", start=1, step=4, preset="kitti")  # kitti preset: grey
    frames = list(stepped)
    assert [f.seq for f in frames] == [1, 5, 9] and frames[0].left.ndim == 2
    assert [abs(float(f.left.mean()) - (10 * f.seq + 5)) < 3 for f in frames] == [True] * 3
    stepped.close()


def test_nubot_original_ppm_naming_with_calibration_file(tmp_path):
    for k in range(12):  # k not zero-padded: 10L.ppm must come after 9L.ppm
        colour = cv2.cvtColor(pattern(k), cv2.COLOR_GRAY2BGR)
        write_png(tmp_path / f"{k}L.ppm", colour)
        write_png(tmp_path / f"{k}R.ppm", colour // 2)
    calibration = Camera(493.86945, 493.86945, 320.33392, 244.18816, 0.11996)
    write_calibration(tmp_path / "calibration.toml", calibration)
    source = open_source(f"stereo:{tmp_path}")
    assert source.camera == Camera(493.86945, 493.86945, 320.33392, 244.18816, 0.11996, 32, 24)
    assert [f.seq for f in source][-3:] == [9, 10, 11]
    frame = source[10]
    assert frame.left.shape == (24, 32, 3) and frame.left[0, 0, 0] == 105 and frame.right[0, 0, 0] == 52
    grey = open_source(f"stereo:{tmp_path}", preset="nubot", stop=2, calibration=Camera(500, 500, 16, 12, 0.1))
    assert grey[1].left.shape == (24, 32) and grey.camera.fx == 500


def test_calibration_file_round_trip(tmp_path):
    camera = Camera(fx=400.5, fy=401.0, cx=200.0, cy=150.25, baseline=0.2, width=400, height=300)
    write_calibration(tmp_path / "cam.toml", camera)
    assert read_calibration(tmp_path / "cam.toml") == camera
    (tmp_path / "mono.toml").write_text("fx = 300\nfy = 300\ncx = 160\ncy = 120\n")
    assert read_calibration(tmp_path / "mono.toml") == Camera(300, 300, 160, 120)


# --- bad input ---------------------------------------------------------------------------


def make_stereo(folder: Path, frames: int = 4) -> Path:
    for k in range(frames):
        write_png(folder / "left" / f"{k:06d}.png", pattern(k))
        write_png(folder / "right" / f"{k:06d}.png", pattern(k))
    return folder


def error_of(spec: str, **kwargs) -> str:
    with pytest.raises(SourceError) as caught:
        open_source(spec, **kwargs)
    return str(caught.value)


def test_missing_folders_and_files(tmp_path):
    missing = tmp_path / "nowhere"
    for kind in ("kitti", "stereo", "images", "video"):
        assert str(missing) in error_of(f"{kind}:{missing}")
    (tmp_path / "left").mkdir()
    assert str(tmp_path / "right") in error_of(f"stereo:{tmp_path}")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert str(empty) in error_of(f"images:{empty}")
    assert "no image_0/ or image_l/" in error_of(f"kitti:{empty}")


def test_unreadable_first_image_names_the_file(tmp_path):
    make_stereo(tmp_path)
    (tmp_path / "left" / "000000.png").write_bytes(b"not a png at all")
    message = error_of(f"stereo:{tmp_path}")
    assert "000000.png" in message and "not a readable image" in message


def test_unreadable_frame_mid_sequence_is_skipped_with_a_warning(tmp_path, caplog):
    make_stereo(tmp_path, frames=6)
    broken = tmp_path / "right" / "000003.png"
    broken.write_bytes(b"\x89PNG truncated")
    source = open_source(f"stereo:{tmp_path}")
    with caplog.at_level(logging.WARNING, logger="services.source.datasets"):
        seqs = [frame.seq for frame in source]
    assert seqs == [0, 1, 2, 4, 5]
    warnings = [record.getMessage() for record in caplog.records if record.levelno == logging.WARNING]
    assert len(warnings) == 1 and str(broken) in warnings[0]
    with pytest.raises(SourceError, match="000003.png"):
        source[3]


def test_mismatched_left_right_sizes(tmp_path):
    make_stereo(tmp_path)
    write_png(tmp_path / "right" / "000000.png", np.zeros((20, 32), np.uint8))
    message = error_of(f"stereo:{tmp_path}")
    assert str(tmp_path / "right" / "000000.png") in message and "32×20" in message and "32×24" in message


def test_image_size_against_calibration(tmp_path):
    make_stereo(tmp_path)
    message = error_of(f"stereo:{tmp_path}", preset="nubot")
    assert "32×24" in message and "640×480" in message


def test_kitti_calibration_with_wrong_number_of_values(tmp_path):
    sequence = make_kitti_root(tmp_path)
    (sequence / "calib.txt").write_text(KITTI_CALIB.replace("-378 0 710", "-378 710") + "\n")
    message = error_of(f"kitti:{sequence}")
    assert str(sequence / "calib.txt") in message and "line 2" in message and "P1 has 11 values" in message
    (sequence / "calib.txt").write_text(KITTI_CALIB.replace("P0: 700", "P0: seven") + "\n")
    assert "line 1" in error_of(f"kitti:{sequence}")


def test_kitti_poses_and_times_must_match_the_images(tmp_path):
    sequence = make_kitti_root(tmp_path, frames=5)
    poses = tmp_path / "poses" / "07.txt"
    poses.write_text(poses.read_text().splitlines()[0] + "\n")
    assert str(poses) in error_of(f"kitti:{sequence}") and "1 lines" in error_of(f"kitti:{sequence}")
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1\n" * 5)
    assert "line 1: 11 values, expected 12" in error_of(f"kitti:{sequence}")
    make_kitti_root(tmp_path / "other", frames=3)
    (tmp_path / "other" / "sequences" / "08").mkdir()
    assert "choose one sequence" in error_of(f"kitti:{tmp_path / 'other'}")


def test_bad_calibration_files(tmp_path):
    make_stereo(tmp_path / "data")
    bad = tmp_path / "cam.toml"
    bad.write_text("fx = 300\nfy = 300\ncx = 160\n")
    assert str(bad) in error_of(f"stereo:{tmp_path / 'data'}", calibration=bad) and "'cy' is missing" in error_of(
        f"stereo:{tmp_path / 'data'}", calibration=bad
    )
    bad.write_text("fx = 300\nfy = 300\ncx = 160\ncy = 120\nbaseline_m = 0.1\n")
    assert "unknown calibration key 'baseline_m'" in error_of(f"stereo:{tmp_path / 'data'}", calibration=bad)
    bad.write_text("fx = 300\nfy = 'wide'\ncx = 160\ncy = 120\n")
    assert "'fy' is not a finite number" in error_of(f"stereo:{tmp_path / 'data'}", calibration=bad)
    bad.write_text("fx = [300\n")
    assert "not valid TOML" in error_of(f"stereo:{tmp_path / 'data'}", calibration=bad)
    assert "calibration file not found" in error_of(f"stereo:{tmp_path / 'data'}", calibration=tmp_path / "none.toml")


def test_bad_video_file(tmp_path):
    garbage = tmp_path / "clip.avi"
    garbage.write_bytes(b"RIFF....AVI garbage" * 10)
    message = error_of(f"video:{garbage}")
    assert str(garbage) in message


def test_bad_specs_selections_and_presets(tmp_path):
    make_stereo(tmp_path, frames=4)
    assert "KIND one of" in error_of(f"folder:{tmp_path}")
    assert "KIND one of" in error_of(str(tmp_path))
    assert "seed must be an integer" in error_of("synthetic:abc")
    assert "selects none of its 4 frames" in error_of(f"stereo:{tmp_path}", start=4)
    assert "invalid frame selection" in error_of(f"stereo:{tmp_path}", step=0)
    with pytest.raises(ConfigError, match="unknown source preset 'nubbot'"):
        open_source(f"stereo:{tmp_path}", preset="nubbot")
    preset = tmp_path / "mine.toml"
    preset.write_text("fps = 5.0\nexposure = 3\n")
    with pytest.raises(ConfigError, match="unknown key 'exposure'"):
        open_source(f"stereo:{tmp_path}", preset=preset)
    preset.write_text("fps = 'fast'\n")
    with pytest.raises(ConfigError, match="'fps' must be float"):
        open_source(f"stereo:{tmp_path}", preset=preset)
    preset.write_text("fps = 5.0\nlaps = 3\n")
    with pytest.raises(ConfigError, match="synthetic world only"):
        open_source(f"stereo:{tmp_path}", preset=preset)
    preset.write_text("fps = 5.0\n")
    assert open_source(f"stereo:{tmp_path}", preset=preset)[2].stamp == pytest.approx(0.4)


# --- live camera -------------------------------------------------------------------------


class FakeCapture:
    """A device delivering a frame every ``period`` seconds; pixel values encode the frame count."""

    def __init__(self, device, period: float = 0.001, fail_after: int | None = None, opened: bool = True):
        self.period, self.fail_after, self.opened = period, fail_after, opened
        self.count = 0
        self.released = threading.Event()

    def isOpened(self) -> bool:
        return self.opened

    def read(self):
        time.sleep(self.period)
        if self.fail_after is not None and self.count >= self.fail_after:
            return False, None
        image = np.full((6, 8, 3), self.count % 256, np.uint8)
        self.count += 1
        return True, image

    def release(self) -> None:
        self.released.set()


def test_live_camera_keeps_only_the_newest_frame():
    capture = FakeCapture(0)
    with LiveCamera(0, capture_factory=lambda device: capture, grey=True) as camera:
        frames, newest_when_asked = [], []
        iterator = iter(camera)
        for _ in range(5):
            # A consumer much slower than the camera: wait until it has grabbed 5 more frames
            # (by count, not by time, so a loaded machine cannot make the test pass or fail).
            target = camera.frames_grabbed + 5
            deadline = time.monotonic() + 10
            while camera.frames_grabbed < target and time.monotonic() < deadline:
                time.sleep(0.002)
            newest_when_asked.append(camera.frames_grabbed - 1)
            frame = next(iterator)
            frames.append(frame)
            assert frame.left[0, 0] == frame.seq % 256 and frame.left.ndim == 2
        seqs = [frame.seq for frame in frames]
        # The frame handed out is the newest one grabbed when it was asked for, not one queued
        # long ago: the frames in between are dropped (gaps), never a backlog.
        assert all(seq >= newest for seq, newest in zip(seqs, newest_when_asked)), (seqs, newest_when_asked)
        assert all(b - a >= 5 for a, b in zip(seqs, seqs[1:])), seqs
        assert camera.frames_dropped >= seqs[-1] - len(seqs)
        assert camera.frames_grabbed >= camera.frames_dropped + len(frames)
        assert [f.stamp for f in frames] == sorted(f.stamp for f in frames)
    assert capture.released.is_set()


def test_live_camera_selection_and_limits():
    camera = LiveCamera(0, capture_factory=lambda device: FakeCapture(device, period=0.002), start=3, stop=12, step=4)
    assert len(camera) == 3
    seqs = [frame.seq for frame in camera]
    assert seqs and all(3 <= s < 12 for s in seqs) and all(b - a >= 4 for a, b in zip(seqs, seqs[1:]))
    with pytest.raises(TypeError, match="no indexed access"):
        camera[0]
    camera.close()
    endless = LiveCamera("/dev/video9", capture_factory=FakeCapture, camera=Camera(100, 100, 4, 3))
    assert endless.camera.width == 8 and endless.camera.height == 6
    with pytest.raises(TypeError, match="no length"):
        len(endless)
    endless.close()


def test_live_camera_errors():
    with pytest.raises(SourceError, match="camera 2: cannot open"):
        LiveCamera(2, capture_factory=lambda device: FakeCapture(device, opened=False))
    with pytest.raises(SourceError, match="camera 0: 50 failed reads in a row"):
        LiveCamera(0, capture_factory=lambda device: FakeCapture(device, period=0.0, fail_after=0))
    with pytest.raises(SourceError, match="calibration is for 640×480"):
        LiveCamera(0, capture_factory=FakeCapture, camera=Camera(500, 500, 320, 240, 0, 640, 480))
    dying = LiveCamera(0, capture_factory=lambda device: FakeCapture(device, period=0.0, fail_after=20))
    with pytest.raises(SourceError, match="stopped delivering"):
        for _ in dying:
            time.sleep(0.002)
    dying.close()
