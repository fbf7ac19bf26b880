"""Monocular odometry: exact motions of a rendered room, the three sources of scale, and
frames it cannot use."""

import math

import numpy as np
import pytest

from services.egomotion import make_estimator
from services.common.frames import Frame
from services.benchmarks.box_room import pinhole, sequence

CAMERA = pinhole(320, 240, fov_deg=70.0)
GROUND = {"scale_source": "ground", "camera_height_m": 1.2, "ground_margin_px": 20.0, "bucket_size_px": 32}


def run(frames, params):
    estimator = make_estimator("mono", CAMERA, params)
    return [estimator.estimate(frame) for frame in frames]


@pytest.fixture(scope="module")
def translation_frames():
    return sequence([(0.10, 0.0, 0.0)] * 4, CAMERA, with_odometry=True)


@pytest.fixture(scope="module")
def rotation_frames():
    return sequence([(0.0, 0.0, math.radians(3.0)), (0.0, 0.0, math.radians(-4.0))], CAMERA, with_odometry=True)


def test_pure_rotation_has_no_translation(rotation_frames):
    for params in ({"scale_source": "none"}, GROUND):
        increments = run(rotation_frames, params)[1:]
        for increment, yaw in zip(increments, (3.0, -4.0)):
            assert math.degrees(increment.yaw) == pytest.approx(yaw, abs=0.05)
            assert (increment.forward, increment.left) == (0.0, 0.0)
            assert increment.quality > 0.5


def test_pure_translation_scaled_by_odometry_speed(translation_frames):
    increments = run(translation_frames, {"scale_source": "auto", "bucket_size_px": 32})[1:]
    for increment in increments:
        assert increment.scaled
        assert increment.forward == pytest.approx(0.10, abs=2e-3)
        assert abs(increment.left) < 0.01
        assert abs(math.degrees(increment.yaw)) < 0.3


def test_pure_translation_scaled_by_ground_plane(translation_frames):
    frames = [Frame(f.seq, f.stamp, f.left, None, CAMERA, f.ground_truth) for f in translation_frames]  # no odometry
    increments = run(frames, GROUND)[1:]
    forward = np.array([increment.forward for increment in increments])
    assert all(increment.scaled for increment in increments)
    assert np.all(np.abs(forward - 0.10) < 0.015)  # camera 1.2 m above a textured floor


def test_without_scale_the_direction_is_unit_and_flagged(translation_frames):
    frames = [Frame(f.seq, f.stamp, f.left, None, CAMERA) for f in translation_frames]
    increments = run(frames, {"scale_source": "none"})[1:]
    for increment in increments:
        assert not increment.scaled
        assert math.hypot(increment.forward, increment.left) == pytest.approx(1.0, abs=0.02)
        assert increment.forward > 0.98


def test_blank_frames_give_low_quality_not_errors(translation_frames):
    blank = np.zeros((240, 320), np.uint8)
    frames = [translation_frames[0], Frame(1, 0.1, blank, None, CAMERA), Frame(2, 0.2, blank, None, CAMERA), translation_frames[1]]
    increments = run(frames, GROUND)
    assert [increment.quality for increment in increments[1:]] == [0.0, 0.0, 0.0]
    assert all(increment.forward == 0.0 and increment.yaw == 0.0 for increment in increments)
