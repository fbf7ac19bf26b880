"""The head-direction ring attractor: a bump that holds still, turns as calibrated, and says
when a yaw is beyond its range."""

import math

import numpy as np
import pytest

from services.common.errors import ConfigError
from services.gridcells.heading import HeadDirectionRing, RingHeading, RingParams, ring_calibration


def test_bump_forms_and_decodes_its_start():
    ring = HeadDirectionRing(heading0=1.2)
    rates = ring.rates
    assert 0 < np.count_nonzero(rates) < len(rates)  # a bump, not uniform activity
    assert ring.heading == pytest.approx(1.2, abs=1e-3)
    assert RingHeading(heading0=-2.5).heading == pytest.approx(-2.5, abs=1e-12)


def test_calibration_is_odd_and_increasing():
    calibration = ring_calibration()
    assert calibration.turns[0] == 0 and np.all(np.diff(calibration.turns) > 0)
    tilt, clipped = calibration.tilt_for(-0.05)
    assert tilt < 0 and not clipped
    assert calibration.tilt_for(0.05)[0] == pytest.approx(-tilt)
    assert calibration.tilt_for(2 * calibration.max_turn)[1]


@pytest.mark.parametrize("yaw_deg", [0.5, 3.0, -8.0])
def test_ring_follows_a_constant_turn(yaw_deg):
    ring = RingHeading(0.3)
    summed = 0.3
    for _ in range(100):
        heading, clipped = ring.step(math.radians(yaw_deg))
        summed += math.radians(yaw_deg)
        assert not clipped
    assert math.degrees(abs(math.remainder(heading - summed, 2 * math.pi))) < 0.05


def test_still_ring_moves_by_less_than_a_cell():
    params = RingParams()
    ring = RingHeading(0.3, params)
    for _ in range(300):
        heading, _ = ring.step(0.0)
    assert abs(heading - 0.3) < math.pi / params.cells  # half a cell spacing: the bump sticks to the cells


def test_checkpoint_restores_the_bump():
    ring = RingHeading(0.0)
    for _ in range(5):
        ring.step(0.1)
    saved = ring.checkpoint()
    expected = ring.step(0.02)[0]
    other = RingHeading(1.0)
    other.restore(saved)
    assert other.step(0.02)[0] == expected


def test_bad_ring_parameters():
    with pytest.raises(ConfigError, match="j1"):
        RingParams(j1=1.5)
    with pytest.raises(ConfigError, match="j0"):
        RingParams(j0=0.5)


def test_a_yaw_beyond_the_ring_frame_limit_takes_several_ring_frames():
    """A walk reflected off a wall turns by up to 180° in one frame: the heading model splits
    it over ring frames of at most 30° and keeps up."""
    ring = RingHeading(0.0)
    heading, clipped = ring.step(math.radians(170))
    assert not clipped
    assert math.degrees(abs(math.remainder(heading - math.radians(170), 2 * math.pi))) < 0.2
