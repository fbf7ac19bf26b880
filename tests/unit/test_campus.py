"""The campus layout of the synthetic world: a network of loops with junctions, a tour of more
than 2 km that stays inside the corridors, revisits both ways, look-alike places, lighting that
changes between visits, determinism and exact odometry."""

from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np
import pytest

from services.source.world import campus
from services.source.spec import load_preset
from services.source.synthetic import SyntheticWorld, WorldConfig
from services.source.world.revisits import revisits


def campus_config(**changes) -> WorldConfig:
    _, settings = load_preset("campus")
    return dataclasses.replace(WorldConfig(**settings), **changes)


@pytest.fixture(scope="module")
def world() -> SyntheticWorld:
    return SyntheticWorld(campus_config(), mono=True)


@pytest.fixture(scope="module")
def found(world) -> list:
    return revisits(world)


def test_loops_of_different_shapes_share_junctions():
    edges = campus.edges()
    degree = collections.Counter(node for edge in edges for node in edge)
    assert set(degree) == set(campus.NODES)  # the tour drives every corridor
    assert len(edges) - len(campus.NODES) + 1 >= 4  # independent loops of the network
    assert sum(d == 3 for d in degree.values()) >= 4 and sum(d == 4 for d in degree.values()) == 1  # T junctions, an X
    assert campus.ARCS  # a curved corridor


def test_route_is_long_and_stays_inside_the_corridors(world):
    assert world.route.length >= 2000
    poses = world.poses
    assert len(world) == len(poses) == world.frames_per_lap
    assert world.layout.is_free(poses[:, 0], poses[:, 1]).all()
    # Never near a wall: the nearest wall segment is farther than the corridor's half width
    # minus pillars and sway (and the right camera of a stereo pair, 0.12 m away, too).
    nearest = np.array([world._segment_distance(x, y).min() for x, y, _ in poses[::3]])
    assert nearest.min() > 0.9
    # Laps close exactly: the route ends where it starts, heading the same way (whole turns apart).
    (x0, y0, h0, _), (x1, y1, h1, _) = world.route.at(0.0), world.route.at(world.route.length - 1e-9)
    assert (x1, y1, math.remainder(h1 - h0, 2 * math.pi)) == pytest.approx((x0, y0, 0.0), abs=1e-6)
    assert h1 - h0 == pytest.approx(world.route.lap_turn, abs=1e-6)


def test_speed_drops_in_turns(world):
    config = world.config
    poses = world.poses
    turn = np.degrees(np.abs(np.diff(poses[:, 2])))
    step = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert turn.max() < config.max_turn_deg * 1.1  # the sway adds a little
    assert np.median(step) == pytest.approx(config.speed, rel=0.02)  # full speed on the straights
    assert step[turn > 0.8 * config.max_turn_deg].max() < 0.5 * config.speed


def test_odometry_composes_to_ground_truth(world):
    x, y, yaw = world.planar_pose(0)
    for seq in range(5, 400, 5):  # turns included
        forward, left, turn = world.odometry(seq - 5, seq)
        x += math.cos(yaw) * forward - math.sin(yaw) * left
        y += math.sin(yaw) * forward + math.cos(yaw) * left
        yaw += turn
    assert (x, y, yaw) == pytest.approx(world.planar_pose(395), abs=1e-9)
    np.testing.assert_allclose(world[395].ground_truth, np.linalg.inv(world.camera_matrix(0)) @ world.camera_matrix(395), atol=1e-9)


def test_revisits_in_both_directions_and_lookalikes(world, found):
    real = [r for r in found if not r.lookalike]
    long_ones = collections.Counter(r.direction for r in real if r.length > 20)
    assert long_ones["same"] >= 5 and long_ones["opposite"] >= 5
    # The same place: within half a frame's travel and the sway.
    assert all(r.distance < world.speed / 2 + 2 * world.config.wander + 0.05 for r in real)
    for r in real:  # the matched frames really stand at the same place, more than 30 m of route apart
        (a, _), (c, _) = r.frames, r.earlier
        assert np.hypot(*(world.poses[a, :2] - world.poses[c, :2])) < 1.0
        assert world.distance(a) - world.distance(c) > 30
    lookalikes = [r for r in found if r.lookalike]
    offsets = sorted({round(math.hypot(*t.offset), 1) for t in world.layout.twins})
    assert {round(r.distance, 1) for r in lookalikes if r.direction == "same"} >= set(offsets)
    assert min(offsets) > 30


def test_lookalike_stretches_look_the_same(world):
    for twin in world.layout.twins:
        x0, x1, y0, y1 = twin.region
        along_x = x1 - x0 > y1 - y0
        x, y = (x0 + 1.0, (y0 + y1) / 2) if along_x else ((x0 + x1) / 2, y0 + 1.0)
        yaw = 0.0 if along_x else math.pi / 2
        original, depth = world.render(x, y, yaw)
        copy, _ = world.render(x + twin.offset[0], y + twin.offset[1], yaw)
        # The same walls (the same texture coordinates) wherever the walls are near...
        near = depth[120] < 8.0
        strip_a = world._cast(x, y, yaw)[1]
        strip_b = world._cast(x + twin.offset[0], y + twin.offset[1], yaw)[1]
        assert np.abs(strip_a - strip_b)[near].max() < 0.05
        # ... and the same image where the view stays inside the stretch, unlike a few metres on.
        rows_near = depth < 8.0
        same = np.abs(original.astype(float) - copy.astype(float))[rows_near].mean()
        step = (3.0, 0.0) if along_x else (0.0, 3.0)
        elsewhere, _ = world.render(x + step[0], y + step[1], yaw)
        assert same < 2.0 < 10.0 < np.abs(original.astype(float) - elsewhere.astype(float))[rows_near].mean()


def test_lighting_differs_between_visits(world, found):
    revisit = next(r for r in found if not r.lookalike and r.direction == "same" and r.length > 20)
    later, earlier = revisit.frames[0] + 5, revisit.earlier[0] + 5
    pose = world.planar_pose(later)
    now = world.render(*pose, time=later / world.config.fps)[0].astype(float)
    before = world.render(*pose, time=earlier / world.config.fps)[0].astype(float)
    again = world.render(*pose, time=later / world.config.fps)[0].astype(float)
    assert np.array_equal(now, again)
    # Not only the overall level: the images differ after normalising their means.
    assert np.abs(now / now.mean() - before / before.mean()).mean() > 0.03
    level, on = world.lighting(later / world.config.fps)
    assert 0 < (on < 1).mean() < 1 and 0.8 < level < 1.2
    assert world.lighting(None) == (1.0, pytest.approx(np.ones(len(world.lamps))))


def test_deterministic_for_a_seed(world):
    again = SyntheticWorld(campus_config(), mono=True, start=1234, stop=1236)
    np.testing.assert_array_equal(again[1].left, world[1235].left)
    other = SyntheticWorld(campus_config(seed=1), mono=True, stop=2)
    assert np.abs(other[0].left.astype(float) - world[0].left.astype(float)).mean() > 10
    np.testing.assert_allclose(other.poses[:50], world.poses[:50])  # the layout and route are fixed


def test_world_settings_are_checked():
    from services.common.errors import ConfigError

    with pytest.raises(ConfigError, match="layout"):
        SyntheticWorld(campus_config(layout="maze"))
    with pytest.raises(ConfigError, match="corridor_width"):
        SyntheticWorld(campus_config(corridor_width=6.0))
    with pytest.raises(ConfigError, match="lamps_off"):
        SyntheticWorld(campus_config(lamps_off=1.0))
