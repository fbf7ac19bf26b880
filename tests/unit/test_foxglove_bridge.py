"""The Foxglove bridge's egomotion track: the increments dead-reckoned as egomotion.tum has them."""

from __future__ import annotations

import math

import pytest

from tests.extras import require

require("foxglove", "foxglove")

from schemas import EgoMotion, Header, PlanarIncrement, Time  # noqa: E402
from services.common.runtime import RuntimeConfig  # noqa: E402
from services.evaluation.trajectory import integrate_increments  # noqa: E402
from services.ros.foxglove import FoxgloveConfig, FoxgloveService  # noqa: E402


def test_egomotion_poses_compose_the_increments_and_restart_with_a_new_run():
    service = FoxgloveService(RuntimeConfig(), FoxgloveConfig(port=0), "test")
    poses = []
    service.ros.planar_pose = lambda stage, stamp, x, y, heading: poses.append((stage, x, y, heading)) or []
    increments = [(0.0, 0.0, 0.0)] + [(0.1, 0.01, math.radians(5))] * 30
    try:
        for _ in range(2):   # the second run starts again at seq 0: a new track from the origin
            for seq, (forward, left, yaw) in enumerate(increments):
                service.on_egomotion(EgoMotion(header=Header(seq=seq, stamp=Time.from_seconds(0.1 * seq)),
                                               increment=PlanarIncrement(forward=forward, left=left, yaw=yaw),
                                               quality=1.0, estimator="passthrough"))
    finally:
        service.teardown()
    truth = integrate_increments(*zip(*increments))
    x, y, heading = truth.planar()
    assert len(poses) == 2 * len(increments) and {stage for stage, *_ in poses} == {"egomotion"}
    for offset in (0, len(increments)):
        got = poses[offset:offset + len(increments)]
        assert [p[1] for p in got] == pytest.approx(list(x), abs=1e-9)
        assert [p[2] for p in got] == pytest.approx(list(y), abs=1e-9)
        assert [math.remainder(p[3] - h, math.tau) for p, h in zip(got, heading)] == pytest.approx([0.0] * len(got), abs=1e-9)
