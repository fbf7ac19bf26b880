"""The path integrator: frames, eq. 5, the velocity scale, saturation and bad input."""

import math

import numpy as np
import pytest

from services.common.odometry import MotionError
from services.gridcells.integrator import (
    DeadReckoning,
    GridCellError,
    GridCellIntegrator,
    auto_velocity_scale,
    TARGET_SHIFT,
)


def test_dead_reckoning_rotates_body_increments_by_the_updated_heading():
    odometry = DeadReckoning()
    odometry.step(1.0, 0.0, 0.0)
    step = odometry.step(1.0, 0.0, math.pi / 2)  # turn left, then move forward: world +y
    assert (step.pose.x, step.pose.y) == pytest.approx((1.0, 1.0))
    assert step.pose.heading == pytest.approx(math.pi / 2)
    step = odometry.step(0.0, 2.0, math.pi)  # heading wraps to -pi/2; "left" is then world +x
    assert step.pose.heading == pytest.approx(-math.pi / 2)
    assert (step.pose.x, step.pose.y, step.step_length) == pytest.approx((3.0, 1.0, 2.0))


@pytest.mark.parametrize("decoder", ["subpixel", "fft"])
def test_straight_walk_follows_the_lattice_direction(decoder):
    heading = math.radians(30)
    speed = 0.5  # m per frame; the scale puts the lattice at TARGET_SHIFT neurons per frame
    scale = auto_velocity_scale([speed], target_shift=TARGET_SHIFT)
    integrator = GridCellIntegrator(decoder=decoder, velocity_scale=scale, heading0=heading)
    for _ in range(8):
        step = integrator.step(speed, 0.0, 0.0)
        assert not step.saturated
        assert math.hypot(*step.shift) == pytest.approx(TARGET_SHIFT, rel=0.25)
    # Every frame counts (the first is compared with the settled field).
    distance = math.hypot(integrator.pose.x, integrator.pose.y)
    assert distance == pytest.approx(8 * speed, rel=0.002 if decoder == "subpixel" else 0.03)
    bearing = math.atan2(integrator.pose.y, integrator.pose.x)
    tolerance = 0.03 if decoder == "subpixel" else 0.25  # integer shifts quantise the direction
    assert abs(bearing - heading) < tolerance
    assert integrator.saturations == 0


def test_paper_first_frame_only_stores_the_pattern():
    integrator = GridCellIntegrator(decoder="paper", velocity_scale=40.0)
    first = integrator.step_world(0.002, 0.0)
    assert (first.pose.x, first.pose.y, first.step_length, first.shift) == (0.0, 0.0, 0.0, (0.0, 0.0))
    second = integrator.step_world(0.002, 0.0)
    assert second.shift[0] > 0 and second.shift[1] == 0.0
    assert (second.pose.x, second.pose.y) == pytest.approx((0.002, 0.0))


def test_rat_and_car_speeds_both_stay_in_range():
    rng = np.random.default_rng(3)
    for typical in (0.001, 1.2):  # a rat at 0.1 cm per frame, a car at 1.2 m per frame
        speeds = typical * rng.uniform(0.5, 1.0, 200)
        integrator = GridCellIntegrator(velocity_scale=auto_velocity_scale(speeds))
        shifts = [math.hypot(*integrator.step_world(s, 0.0).shift) for s in speeds[:6]]
        assert 1.0 < np.median(shifts[1:]) < 4.0, (typical, shifts)
        assert integrator.saturations == 0


def test_saturating_speed_is_flagged_and_counted(caplog):
    integrator = GridCellIntegrator(velocity_scale=1.0)
    steps = [integrator.step_world(0.6, 0.3) for _ in range(3)]  # α|v| = 1.34, far beyond linear
    assert all(step.saturated for step in steps)
    assert integrator.saturations == 3
    assert "saturated" in caplog.text


@pytest.mark.parametrize("call", [
    lambda g: g.step(float("nan"), 0.0, 0.0),
    lambda g: g.step(0.1, 0.0, float("inf")),
    lambda g: g.step_world(0.1, float("-inf")),
    lambda g: g.step_world(0.1, 0.0, heading=float("nan")),
])
def test_non_finite_input_is_a_clear_error(call):
    for integrator, error in ((GridCellIntegrator(), GridCellError), (DeadReckoning(), MotionError)):
        with pytest.raises(error, match="expected a finite number"):
            call(integrator)


def test_bad_configuration_is_an_error():
    with pytest.raises(GridCellError, match="unknown decoder"):
        GridCellIntegrator(decoder="nearest")
    with pytest.raises(GridCellError, match="velocity scale"):
        GridCellIntegrator(velocity_scale=0.0)
    with pytest.raises(GridCellError, match="not finite"):
        auto_velocity_scale([0.1, float("nan")])
    assert auto_velocity_scale([0.0, 0.0]) == 1.0


def test_auto_scale_follows_the_documented_rule():
    speeds = np.r_[np.zeros(50), np.linspace(0.01, 0.1, 100)]  # standing frames are ignored
    expected = TARGET_SHIFT / (0.383 * 2.0 * 50 * np.percentile(np.linspace(0.01, 0.1, 100), 95))
    assert auto_velocity_scale(speeds) == pytest.approx(expected)


def test_se2_increments_turned_for_the_integrator_give_the_se2_path():
    """EgoMotion increments move in the body frame before the frame's yaw (SE(2) composition);
    turn_first turns them so that the integrators (turn, then move) follow the same path."""
    from services.evaluation.trajectory import integrate_increments
    from services.gridcells.integrator import turn_first

    rng = np.random.default_rng(0)
    forward, left, yaw = rng.uniform(0.05, 0.15, 50), rng.normal(0, 0.01, 50), rng.normal(0, 0.1, 50)
    truth = integrate_increments(forward, left, yaw)
    odometry = DeadReckoning()
    for f, l, y in zip(forward, left, yaw):
        step = odometry.step(*turn_first(f, l, y), y)
    assert (step.pose.x, step.pose.y) == pytest.approx(tuple(truth.positions[-1, :2]), abs=1e-12)


def test_ring_heading_drives_the_integrator_and_survives_a_checkpoint():
    integrator = GridCellIntegrator(velocity_scale=10.0, heading="ring")
    for _ in range(10):
        step = integrator.step(0.01, 0.0, math.radians(2))
    assert step.pose.heading == pytest.approx(math.radians(20), abs=math.radians(0.05))
    saved = integrator.checkpoint()
    expected = integrator.step(0.01, 0.0, 0.01)
    other = GridCellIntegrator(velocity_scale=10.0, heading="ring")
    other.restore(saved)
    again = other.step(0.01, 0.0, 0.01)
    assert (again.pose.x, again.pose.y, again.pose.heading) == pytest.approx((expected.pose.x, expected.pose.y, expected.pose.heading), abs=1e-9)
