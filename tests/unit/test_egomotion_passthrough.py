"""Passthrough: exact increments from odometry or ground truth, and seeded noise."""

import math

import numpy as np
import pytest

from services.egomotion import EgomotionError, make_estimator
from services.common.frames import Frame
from services.benchmarks.box_room import motion_pose

STEPS = [(0.2, 0.01, math.radians(4.0)), (0.3, -0.02, math.radians(-2.0)), (0.1, 0.0, 0.0)]


def frames(with_odometry: bool, with_truth: bool):
    image = np.zeros((4, 4), np.uint8)
    pose = np.eye(4)
    result = [Frame(0, 0.0, image, ground_truth=pose if with_truth else None, odometry=(0.0, 0.0, 0.0) if with_odometry else None)]
    for k, step in enumerate(STEPS, start=1):
        pose = pose @ motion_pose(*step)
        result.append(Frame(k, 0.1 * k, image, ground_truth=pose if with_truth else None, odometry=step if with_odometry else None))
    return result


@pytest.mark.parametrize("source,odometry,truth", [("odometry", True, False), ("ground_truth", False, True), ("auto", False, True)])
def test_exact_increments(source, odometry, truth):
    estimator = make_estimator("passthrough", None, {"source": source})
    increments = [estimator.estimate(frame) for frame in frames(odometry, truth)]
    assert (increments[0].forward, increments[0].yaw) == (0.0, 0.0)
    got = np.array([(i.forward, i.left, i.yaw) for i in increments[1:]])
    assert np.allclose(got, STEPS, atol=1e-12)


def test_noise_is_seeded_with_the_given_deviation():
    many = [Frame(k, 0.1 * k, np.zeros((2, 2), np.uint8), odometry=(0.1, 0.0, 0.0)) for k in range(2001)]
    params = {"noise_forward": 0.01, "noise_left": 0.0, "noise_yaw": 0.002, "seed": 5}
    runs = []
    for _ in range(2):
        estimator = make_estimator("passthrough", None, params)
        runs.append(np.array([(i.forward, i.left, i.yaw) for i in map(estimator.estimate, many)][1:]))
    assert np.array_equal(runs[0], runs[1])
    # A frame's noise depends on the frame, not on what the estimator saw before it.
    restarted = make_estimator("passthrough", None, params)
    restarted.estimate(many[999])
    assert (restarted.estimate(many[1000]).forward, restarted.estimate(many[1001]).forward) == tuple(runs[0][999:1001, 0])
    assert runs[0][:, 0].std() == pytest.approx(0.01, rel=0.1) and runs[0][:, 0].mean() == pytest.approx(0.1, abs=1e-3)
    assert np.all(runs[0][:, 1] == 0.0) and runs[0][:, 2].std() == pytest.approx(0.002, rel=0.1)


def test_missing_motion_is_an_error():
    estimator = make_estimator("passthrough", None, {"source": "odometry"})
    with pytest.raises(EgomotionError, match="no odometry"):
        estimator.estimate(frames(False, True)[0])
