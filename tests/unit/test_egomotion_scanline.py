"""RatSLAM scanline odometry: profile matching, exact turns of a rendered room, speed from
the residual, and blank frames."""

import math

import numpy as np
import pytest

from services.egomotion import make_estimator
from services.egomotion.scanline import intensity_profile, match_profiles
from services.common.frames import Frame
from services.benchmarks.box_room import pinhole, sequence

CAMERA = pinhole(320, 240, fov_deg=70.0)


def run(frames, params):
    estimator = make_estimator("scanline", CAMERA, params)
    return [estimator.estimate(frame) for frame in frames]


def test_match_profiles_finds_a_known_shift():
    rng = np.random.default_rng(1)
    previous = np.convolve(rng.random(400), np.ones(5) / 5, mode="same")
    current = np.roll(previous, 7)  # content moved 7 columns to the right
    match = match_profiles(current[20:-20], previous[20:-20], max_shift=40)
    assert match.shift == 7.0 and match.cost == pytest.approx(0.0, abs=1e-12) and match.distinctness > 0.9
    half = 0.5 * (np.roll(previous, 3) + np.roll(previous, 4))  # 3.5 columns, roughly
    assert match_profiles(half[20:-20], previous[20:-20], 40, subpixel=True).shift == pytest.approx(3.5, abs=0.2)


def test_intensity_profile_is_the_column_mean_of_the_crop():
    image = np.tile(np.arange(10, dtype=np.uint8) * 20, (6, 1))
    image[:3] = 0
    profile = intensity_profile(image, 2, 5, 3, -1)
    assert np.allclose(profile, np.array([40, 60, 80]) / 255.0)


@pytest.fixture(scope="module")
def frames():
    return sequence([(0.0, 0.0, math.radians(3.0)), (0.0, 0.0, math.radians(-6.0)), (0.15, 0.0, 0.0), (0.15, 0.0, 0.0)], CAMERA)


def test_pure_rotation(frames):
    # Equal-angle profiles: every column of a turn moves by the same angle.
    increments = run(frames[:3], {"subpixel": True, "equiangular": True})[1:]
    assert [math.degrees(i.yaw) for i in increments] == pytest.approx([3.0, -6.0], abs=0.05)
    # RatSLAM's own integer shifts over plain columns: right sign, within the stretch of a
    # 70° pinhole view (the edges move up to 1.5 times the centre).
    plain = run(frames[:3], {})[1:]
    assert 3.0 <= math.degrees(plain[0].yaw) <= 4.0 and -7.5 <= math.degrees(plain[1].yaw) <= -6.0


def test_pure_translation_has_speed_and_little_rotation(frames):
    increments = run(frames, {"subpixel": True, "vtrans_scaling": 100.0, "camera_hz": 10.0})
    moving = increments[3:]
    assert all(abs(math.degrees(i.yaw)) < 0.3 for i in moving)
    assert all(i.forward > 0.0 and i.left == 0.0 and i.transform is None for i in moving)
    # Speed is the residual times the scaling, clipped, per frame at camera_hz.
    clipped = run(frames, {"vtrans_scaling": 100.0, "vtrans_max": 0.5, "camera_hz": 10.0})
    assert all(i.forward == pytest.approx(0.05) for i in clipped[3:])
    assert increments[3].match_cost * 100.0 / 10.0 == pytest.approx(increments[3].forward)


def test_first_and_blank_frames_are_still():
    blank = np.full((240, 320), 90, np.uint8)
    increments = run([Frame(k, 0.1 * k, blank) for k in range(3)], {})
    assert all((i.forward, i.yaw, i.quality) == (0.0, 0.0, 0.0) for i in increments)
