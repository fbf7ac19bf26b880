"""The experience map: relaxation with known answers, persistence and recovery of its log, the
export, and the adapter's determinism (services/expmap)."""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import sys
import threading
import time

import numpy as np
import pytest

from schemas import GridPose, Header, LoopClosure, PlanarIncrement, Time, ViewTemplate
from services.cli import main as gridslam
from services.common.convert import planar_pose
from services.common.errors import DataError
from services.common.geometry import between, compose, wrap
from services.common.runtime import RuntimeConfig
from services.evaluation import metrics
from services.evaluation.trajectory import Trajectory, read_tum
from services.expmap.export import MapExportError, export_map, graph_dict, read_log
from services.expmap.graph import ExperienceMap, FrameResult, MapParams
from services.expmap.links import ClosureInput, Link
from services.expmap.service import ExpMapConfig, ExpMapService
from services.expmap.store import (
    CheckpointPolicy,
    MapStore,
    Step,
    checkpoint_path,
    replay,
    write_checkpoint,
)

QUARTER = math.pi / 2


# --- RatSLAM's relaxation (optimizer = ratslam) ------------------------------------------------
RATSLAM = MapParams(optimizer="ratslam", closure="ratslam")


def loop_map(poses, links) -> ExperienceMap:
    """A map under RatSLAM's relaxation holding exactly these experiences and links."""
    experience_map = ExperienceMap(RATSLAM)
    for i, pose in enumerate(poses):
        experience_map._add_experience(pose, i, i, FrameResult(i, i, pose))
    for s_, t, dx, dy, dh, closure in links:
        link = Link(s_, t, dx, dy, dh, frame=t, loop_closure=closure)
        experience_map.optimizer.add_link(link)
        experience_map.links.append(link)
    return experience_map


def test_a_square_with_an_odometry_error_relaxes_to_the_balanced_answer():
    # Four 1 m sides turning left; the odometry of the last side says 1.2 m (a 0.2 m misclosure).
    # Headings agree around the loop, so only positions move: least squares over a cycle of
    # equal links gives every link the same residual, a quarter of the misclosure (0.05 m
    # along +y), and with every experience of degree 2 the centroid (0.5, 0.5) stays put.
    # By hand: p1 = p0 + (1, 0.05), p2 = p0 + (1, 1.1), p3 = p0 + (0, 1.15), p0 = (0, -0.075).
    experience_map = loop_map(
        poses=[(0, 0, 0), (1, 0, QUARTER), (1, 1, 2 * QUARTER), (0, 1, -QUARTER)],
        links=[(0, 1, 1.0, 0, QUARTER, False), (1, 2, 1.0, 0, QUARTER, False), (2, 3, 1.0, 0, QUARTER, False),
               (3, 0, 1.2, 0, QUARTER, True)])
    experience_map.optimizer.relax(2000)
    expected = np.array([(0, -0.075), (1, -0.025), (1, 1.025), (0, 1.075)])
    assert experience_map.poses[:, :2] == pytest.approx(expected, abs=1e-9)
    assert wrap(experience_map.poses[:, 2] - [0, QUARTER, 2 * QUARTER, -QUARTER]) == pytest.approx(np.zeros(4), abs=1e-12)


def test_a_heading_misclosure_is_shared_equally_by_the_links_of_the_loop():
    # Three experiences at one place; the turns around the loop add up to 0.1 rad, not 0.
    experience_map = loop_map(poses=[(0, 0, 0.0), (0, 0, 0.5), (0, 0, 1.0)],
                              links=[(0, 1, 0, 0, 0.5, False), (1, 2, 0, 0, 0.5, False), (2, 0, 0, 0, -0.9, True)])
    experience_map.optimizer.relax(2000)
    headings = experience_map.poses[:, 2]
    # Each link ends up 0.1 / 3 short of its measured turn; the mean heading (0.5) is kept.
    assert np.diff(headings) == pytest.approx([0.5 - 0.1 / 3] * 2, abs=1e-9)
    assert headings.mean() == pytest.approx(0.5, abs=1e-9)
    assert experience_map.poses[:, :2] == pytest.approx(np.zeros((3, 2)), abs=1e-12)


def test_a_snap_onto_the_experience_the_robot_is_at_links_nothing_and_moves_nothing():
    # RatSLAM's model: a match of the current experience confirms where the robot is. A link from
    # the experience to itself would contradict the odometry within it (on the demo 253 of 365
    # such links shrank the map 20 % and left it 21 times the odometry's error).
    experience_map = ExperienceMap(MapParams(new_experience_distance=0.6, optimizer="ratslam", closure="ratslam"))
    experience_map.step(0, (0.0, 0.0, 0.0), 0)
    experience_map.step(1, (0.2, 0.0, 0.0), 0)
    stayed = experience_map.step(2, (0.4, 0.0, 0.0), 0, ClosureInput(0, 0, "none", 0.0, 0.0, 0.0, ()))
    assert stayed.experience == 0 and stayed.offset == pytest.approx((0.4, 0.0, 0.0))
    assert experience_map.links == [] and stayed.closure is None
    experience_map.step(3, (0.8, 0.0, 0.0), 1)   # a new place: experience 1, linked to 0
    # Frame 1's view again (template 0): the robot is back where frame 1 was, on experience 0.
    snapped = experience_map.step(4, (1.0, 0.0, 0.0), 0, ClosureInput(0, 1, "none", 0.0, 0.0, 0.0, ()))
    assert snapped.experience == 0 and snapped.closure == "accepted" and snapped.offset == pytest.approx((0.2, 0.0, 0.0))
    assert [(link.source, link.target, link.loop_closure) for link in experience_map.links] == [(0, 1, False), (1, 0, True)]


# --- driving a square ---------------------------------------------------------------------------
def drive_square(side: float = 2.0, step: float = 0.25, heading_drift: float = 0.0, laps: float = 1.0):
    """Frames driving a square counter-clockwise from the origin: (frame, true pose, odometry
    pose, template id). The odometry's heading drifts by `heading_drift` rad per frame; the
    template changes with the side (so it repeats on a revisit)."""
    frames, per_side = [], int(round(side / step))
    true_pose = odometry = (0.0, 0.0, 0.0)
    count = int(round(4 * per_side * laps))
    for k in range(count + 1):
        frames.append((k, true_pose, odometry, (k // per_side) % 4 if k < count else 0))
        turn = QUARTER if (k + 1) % per_side == 0 else 0.0
        true_pose = compose(true_pose, (step, 0.0, turn))
        odometry = compose(odometry, (step, 0.0, turn + heading_drift))
    return frames


CLOSURE_COVARIANCE = tuple(np.diag([0.02 ** 2, 0.02 ** 2, 0.005 ** 2]).ravel())


def measured(truth: dict, frame: int, template: int, matched_frame: int, method: str = "stereo") -> ClosureInput:
    """A closure whose relative pose is the true one (as the images would measure it)."""
    return ClosureInput(template, matched_frame, method, *between(truth[matched_frame], truth[frame]), CLOSURE_COVARIANCE)


def run_map(frames, params=MapParams(new_experience_distance=0.6), closure_at_end=True) -> ExperienceMap:
    """The square's map with one closure on its last frame, back at the first."""
    experience_map = ExperienceMap(params)
    truth = {frame: pose for frame, pose, _, _ in frames}
    last = frames[-1][0]
    for frame, _, odometry, template in frames:
        closure = measured(truth, frame, 0, 0) if closure_at_end and frame == last else None
        experience_map.step(frame, odometry, template, closure)
    return experience_map


MODELS = {"paper (ratslam, ratslam)": MapParams(new_experience_distance=0.6, optimizer="ratslam", closure="ratslam",
                                                relax_passes=3000),
          "default (gtsam, metric)": MapParams(new_experience_distance=0.6)}


@pytest.mark.parametrize("params", MODELS.values(), ids=MODELS.keys())
def test_a_consistent_loop_does_not_move(params):
    frames = drive_square()
    experience_map = run_map(frames, params)
    assert sum(link.loop_closure and link.accepted for link in experience_map.links) == 1
    truth = np.array([pose for _, pose, _, _ in frames])
    assert experience_map.final_poses()[:, :2] == pytest.approx(truth[experience_map.created][:, :2], abs=1e-6)
    corrected = np.array([row[1:] for row in experience_map.trajectory()])
    assert corrected[:, :2] == pytest.approx(truth[:, :2], abs=1e-6)


def errors(path, truth):
    as_trajectory = [Trajectory.from_planar(np.arange(len(p)), p[:, 0], p[:, 1], p[:, 2]) for p in (path, truth)]
    return metrics.position_errors(*as_trajectory, align="se2")


@pytest.mark.parametrize("params", MODELS.values(), ids=MODELS.keys())
def test_a_closure_pulls_a_drifting_loop_together(params):
    frames = drive_square(heading_drift=0.01)
    odometry = np.array([o for _, _, o, _ in frames])
    truth = np.array([t for _, t, _, _ in frames])
    experience_map = run_map(frames, params)
    assert experience_map.closures["accepted"] == 1
    corrected = np.array([row[1:] for row in experience_map.trajectory()])
    # The end is back at the start (the closure), and the whole path is near the truth: the
    # heading drift is spread over the loop. (The map may move and turn as a whole: SE(2)-aligned.)
    assert np.linalg.norm(odometry[-1, :2] - odometry[0, :2]) > 0.4
    assert np.linalg.norm(corrected[-1, :2] - corrected[0, :2]) < 0.03
    assert errors(odometry, truth).max() > 0.2
    assert errors(corrected, truth).max() < 0.1 * errors(odometry, truth).max()


LOOK_ALIKE = range(200, 208)   # lap 2, side 2 ...
LOOKED_AT = range(8, 16)       # ... looks like lap 1, side 0, 8 m across the square
LAP_CLOSURES = range(128, 136)


def two_laps_with_a_look_alike():
    """Two laps of an 8 m square (128 frames a lap, heading drift 0.001 rad per frame). The true
    closures of lap 2's start (frames 128..135 against 0..7) come first; then, on side 2, the
    robot's views (frames 200..207) are what it saw of side 0 at frames 8..15 — a look-alike
    stretch, measured by the images as if it were there — while the odometry (and the truth) put
    it 8 m away, across the square."""
    frames = drive_square(side=8.0, heading_drift=0.001, laps=2.0)
    truth = {frame: pose for frame, pose, _, _ in frames}
    covariance = tuple(np.diag([0.005 ** 2, 0.005 ** 2, 0.006 ** 2]).ravel())
    steps = []
    for frame, _, odometry, template in frames:
        closure = None
        if frame in LAP_CLOSURES:
            closure = measured(truth, frame, 0, frame - LAP_CLOSURES[0])
        elif frame in LOOK_ALIKE:
            looked_at = LOOKED_AT[frame - LOOK_ALIKE[0]]
            closure = ClosureInput(0, looked_at, "stereo", 0.0, 0.0, 0.0, CLOSURE_COVARIANCE)
        steps.append(Step(frame, 0.1 * frame, odometry, template, closure, covariance if frame else None))
    return frames, steps


def test_a_refused_closure_leaves_the_poses_the_map_publishes_where_they_would_be_without_it():
    # The solve that tests a closure far off tears the map apart; once the closure is taken out
    # the map must settle back before the frame's pose is published (on the campus one such frame
    # was published 6.7 m off, its neighbours 0.08 m). 2.6 laps of a 40 m square closed at
    # every second frame from lap 2 on, then eight closures to the far side, turned half round.
    frames = drive_square(side=40.0, heading_drift=0.005, laps=2.6)
    truth = {frame: pose for frame, pose, _, _ in frames}
    lap = 640
    far_off = range(2 * lap + lap // 2, 2 * lap + lap // 2 + 8)
    covariance = tuple(np.diag([0.005 ** 2, 0.005 ** 2, 0.006 ** 2]).ravel())
    seen, unseen = ExperienceMap(MapParams(new_experience_distance=0.6)), ExperienceMap(MapParams(new_experience_distance=0.6))
    for frame, _, odometry, template in frames:
        step = Step(frame, 0.1 * frame, odometry, template, None, covariance if frame else None)
        if frame in far_off:
            wrong = ClosureInput(0, (frame + lap // 2) % lap, "stereo", 0.0, 0.0, 3.0, CLOSURE_COVARIANCE)
            published = dataclasses.replace(step, closure=wrong).apply(seen)
            assert published.closure == "rejected"
            assert published.pose == pytest.approx(step.apply(unseen).pose, abs=5e-4)
            continue
        if frame >= lap and frame % 2 == 0:
            step = dataclasses.replace(step, closure=measured(truth, frame, 0, frame % lap))
        step.apply(seen)
        step.apply(unseen)


def test_closures_at_a_look_alike_place_far_away_are_refused_and_the_loop_keeps_its_shape():
    frames, steps = two_laps_with_a_look_alike()
    truth = np.array([t for _, t, _, _ in frames])
    experience_map = ExperienceMap(MapParams(new_experience_distance=0.6))
    results = [step.apply(experience_map) for step in steps]
    decided = {step.frame: result.closure for step, result in zip(steps, results) if step.closure is not None}
    assert [decided[f] for f in LAP_CLOSURES] == ["accepted"] * 8
    assert [decided[f] for f in LOOK_ALIKE] == ["rejected"] * 8
    refused = [link for link in experience_map.links if link.loop_closure and not link.accepted]
    assert len(refused) == 8 and all(link.frame in LOOK_ALIKE for link in refused)
    corrected = np.array([row[1:] for row in experience_map.trajectory()])
    # The look-alike stretch stays where it is (metres from side 0), and the loop keeps its shape:
    # the map is the one it would be had the look-alike never been seen.
    assert np.linalg.norm(corrected[LOOK_ALIKE[4], :2] - corrected[LOOKED_AT[4], :2]) > 7.0
    unseen = ExperienceMap(MapParams(new_experience_distance=0.6))
    for step in steps:
        dataclasses.replace(step, closure=None if step.frame in LOOK_ALIKE else step.closure).apply(unseen)
    assert corrected == pytest.approx(np.array([row[1:] for row in unseen.trajectory()]), abs=1e-3)
    assert errors(corrected, truth).max() < errors(np.array([o for _, _, o, _ in frames]), truth).max()
    # Without the refusal (least squares, no test) the look-alike would pull side 2 onto side 0.
    pulled = ExperienceMap(MapParams(new_experience_distance=0.6, closure_gate=1e9, robust_kernel="none"))
    for step in steps:
        step.apply(pulled)
    bent = np.array([row[1:] for row in pulled.trajectory()])
    assert errors(bent, truth).max() > 1.0


def test_a_closure_without_a_measurement_is_counted_and_not_used():
    frames = drive_square(heading_drift=0.01)
    experience_map = ExperienceMap(MapParams(new_experience_distance=0.6))
    for frame, _, odometry, template in frames:
        closure = ClosureInput(0, 0, geometry_error="too few inliers (7 < 20)") if frame == frames[-1][0] else None
        experience_map.step(frame, odometry, template, closure)
    assert experience_map.closures == {"accepted": 0, "rejected": 0, "unmeasured": 1, "unmatched": 0}
    assert not any(link.loop_closure for link in experience_map.links)
    odometry = np.array([o for _, _, o, _ in frames])
    assert np.array([row[1:] for row in experience_map.trajectory()]) == pytest.approx(odometry, abs=1e-9)


def test_a_monocular_closure_takes_its_length_from_the_odometry():
    # Only the direction is measured (a unit vector): the map scales it by its own estimate of the
    # distance, with a wide uncertainty along it, and still closes the loop.
    frames = drive_square(heading_drift=0.01)
    truth = {frame: pose for frame, pose, _, _ in frames}
    experience_map = ExperienceMap(MapParams(new_experience_distance=0.6))
    last = frames[-1][0]
    stop = compose(truth[last], (-0.3, 0.1, 0.0))   # the last frame 0.3 m short of the start
    for frame, _, odometry, template in frames[:-1]:
        experience_map.step(frame, odometry, template)
    forward, left, yaw = between(truth[0], stop)
    norm = math.hypot(forward, left)
    direction = np.array([-left, forward]) / norm
    covariance = np.zeros((3, 3))
    covariance[:2, :2] = 0.02 ** 2 * np.outer(direction, direction)
    covariance[2, 2] = 0.005 ** 2
    odometry_end = compose(frames[-2][2], between(truth[frames[-2][0]], stop))
    result = experience_map.step(last, odometry_end, 0, ClosureInput(0, 0, "mono", forward / norm, left / norm, yaw,
                                                                      tuple(covariance.ravel())))
    assert result.closure == "accepted"
    placed = experience_map.trajectory()[-1][1:]
    assert math.hypot(placed[0] - stop[0], placed[1] - stop[1]) < 0.2


def test_the_odometry_covariance_decides_what_drift_a_closure_may_correct():
    # The same drifting loop and closure: with the odometry's covariance it reports (failed
    # frames, metres of uncertainty) the closure is accepted; with a tight one, refused.
    frames = drive_square(heading_drift=0.05)
    truth = {frame: pose for frame, pose, _, _ in frames}
    for sigma, expected in ((0.5, "accepted"), (0.001, "rejected")):
        covariance = tuple(np.diag([sigma ** 2, sigma ** 2, (sigma / 2) ** 2]).ravel())
        experience_map = ExperienceMap(MapParams(new_experience_distance=0.6))
        for frame, _, odometry, template in frames:
            closure = measured(truth, frame, 0, 0) if frame == frames[-1][0] else None
            result = experience_map.step(frame, odometry, template, closure, covariance if frame else None)
        assert result.closure == expected, sigma


# --- the pose graph's junctions and chains (optimizer = gtsam) ---------------------------------
def least_squares(experience_map: ExperienceMap, initial: np.ndarray, without: int | None = None):
    """The map's whole pose graph, every experience a variable and every link it keeps a factor
    (closures under its kernel), each part's first experience held by its prior, solved in one
    batch from `initial`: its poses and the graph.
    `without`: leave that link out."""
    import gtsam

    state = experience_map.state()
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*state["prior"]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    for key, x, y, heading, sigma in state["part_priors"]:   # the later parts' first experiences
        graph.add(gtsam.PriorFactorPose2(int(key), gtsam.Pose2(x, y, heading), gtsam.noiseModel.Isotropic.Sigma(3, sigma)))
    kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(experience_map.params.kernel_width)
    for index, (link, covariance) in enumerate(zip(experience_map.links, state["covariances"])):
        if link.accepted and index != without:
            noise = gtsam.noiseModel.Gaussian.Covariance(covariance)
            graph.add(gtsam.BetweenFactorPose2(link.source, link.target, gtsam.Pose2(*link.transform),
                                               gtsam.noiseModel.Robust.Create(kernel, noise) if link.loop_closure else noise))
    values = gtsam.Values()
    for index, pose in enumerate(initial):
        values.insert(index, gtsam.Pose2(*pose))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    solution = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return gtsam.utilities.extractPose2(solution), graph, solution


@pytest.mark.parametrize("closure, tolerance", [("metric", 1e-4), ("ratslam", 5e-3)])
def test_the_map_is_the_least_squares_solution_of_its_whole_graph(closure, tolerance):
    # The solver holds only the junctions (the first experience, the ends of the closures, where a
    # snap branches) and one factor per chain of odometry between two of them; a chain's inner
    # experiences are placed by its own least squares. That is the whole graph's solution: two
    # laps of the 8 m square, the heading drifting 0.13 rad a lap, the look-alikes refused. (A
    # chain's misfit shared as its linearised conditional mean put experiences 7 mm off the
    # solution; chain factors kept where the odometry put them, 1 mm. With RatSLAM's snaps, whose
    # wide covariance iSAM2 settles less closely, the map is 2 mm from it; with every experience
    # in the solver it was 5.6 mm, in the metric map 0.4 mm.)
    _, steps = two_laps_with_a_look_alike()
    experience_map = ExperienceMap(MapParams(new_experience_distance=0.6, closure=closure))
    for step in steps:
        step.apply(experience_map)
    assert len(experience_map.state()["junctions"]) < len(experience_map) / 3
    poses = experience_map.final_poses()
    solution, _, _ = least_squares(experience_map, poses)
    assert poses[:, :2] == pytest.approx(solution[:, :2], abs=tolerance)
    assert wrap(poses[:, 2] - solution[:, 2]) == pytest.approx(np.zeros(len(poses)), abs=tolerance / 5)


def test_a_closure_is_tested_by_the_innovation_of_the_whole_graph():
    # νᵀS⁻¹ν with S = Σ + J P Jᵀ, P the whole graph's marginal covariance of the closure's two
    # experiences: the factor of a chain carries the covariance of its links along it.
    frames = drive_square(heading_drift=0.01)
    experience_map = run_map(frames)
    (index, _), = [(i, k) for i, k in enumerate(experience_map.links) if k.loop_closure]
    expected = whole_graph_innovation(experience_map, index)
    assert expected > 1.0   # the loop's drift: a closure the odometry's uncertainty must absorb
    assert experience_map.residuals[-1] == pytest.approx(expected, rel=0.02)


def whole_graph_innovation(experience_map: ExperienceMap, index: int) -> float:
    """The test statistic of the map's link `index` (a closure) computed from the whole graph
    without it: √(νᵀS⁻¹ν), S = Σ + J P Jᵀ."""
    import gtsam

    from services.common.geometry import adjoint, inverse

    link = experience_map.links[index]
    covariance = experience_map.state()["covariances"][index]
    poses, graph, solution = least_squares(experience_map, experience_map.final_poses(), without=index)
    source, target = (gtsam.Pose2(*poses[key]) for key in (link.source, link.target))
    innovation = gtsam.Pose2.Logmap(gtsam.Pose2(*link.transform).between(source.between(target)))
    marginal = gtsam.Marginals(graph, solution).jointMarginalCovariance([link.source, link.target]).fullMatrix()
    relative = between(tuple(poses[link.source]), tuple(poses[link.target]))
    jacobian = np.hstack([-adjoint(inverse(relative)), np.eye(3)])
    return math.sqrt(innovation @ np.linalg.solve(covariance + jacobian @ marginal @ jacobian.T, innovation))


def test_only_the_junctions_are_in_the_solver_and_frames_between_closures_do_not_touch_it():
    from services.benchmarks.mapping import map_stream

    experience_map = ExperienceMap(MapParams())
    updates = []
    for frame, odometry, template, closure, _ in map_stream(3000, 0, 500, 0, 0):   # 3 laps, a closure every 500 frames
        experience_map.step(frame, odometry, template, closure)
        updates.append(experience_map.optimizer.updates)
    assert experience_map.closures["accepted"] == 4   # at frames 1000, 1500, 2000, 2500, each one lap back
    # In the solver: the first experience and the ends of the closures (one experience a frame).
    assert experience_map.state()["junctions"].tolist() == [0, 500, 1000, 1500, 2000, 2500]
    assert all(updates[frame] == updates[frame - 1] for frame in range(1, 3000) if frame % 500)


# --- persistence ------------------------------------------------------------------------------
PARAMS = MapParams(new_experience_distance=0.6)


def square_steps(laps: float = 1.25, drift: float = 0.01) -> list[Step]:
    """Steps of a loop driven 1¼ times, with measured closures on the second lap (each against
    its side's first frame) and each increment's covariance."""
    frames = drive_square(heading_drift=drift, laps=laps)
    truth = {frame: pose for frame, pose, _, _ in frames}
    per_lap = 32
    covariance = tuple(np.diag([0.01 ** 2, 0.01 ** 2, 0.03 ** 2]).ravel())
    return [Step(frame, 0.1 * frame, odometry, template,
                 measured(truth, frame, template, 8 * template) if frame >= per_lap else None, covariance)
            for frame, _, odometry, template in frames]


def write_store(path, steps, params=PARAMS) -> ExperienceMap:
    store, experience_map = MapStore(path, params), ExperienceMap(params)
    for step in steps:
        store.append(step)
        step.apply(experience_map)
    store.close()
    return experience_map


def same_map(a: ExperienceMap, b: ExperienceMap) -> None:
    assert np.array_equal(a.poses, b.poses) and a.closures == b.closures
    assert a.links == b.links and a.templates == b.templates and a.created == b.created
    assert a.trajectory() == b.trajectory()


def test_a_map_rebuilt_from_its_log_equals_the_original(tmp_path):
    steps = square_steps()
    original = write_store(tmp_path / "map.log", steps)
    assert original.closures["accepted"] >= 2
    store = MapStore(tmp_path / "map.log", PARAMS)
    assert store.steps == steps
    same_map(read_log(tmp_path / "map.log").rebuild(), original)
    store.close()


def test_a_torn_last_record_is_skipped_with_a_warning_and_cut(tmp_path, caplog):
    path = tmp_path / "map.log"
    steps = square_steps()
    write_store(path, steps[:-1])
    size = path.stat().st_size
    with open(path, "a") as handle:   # a crash in the middle of writing the last record
        handle.write('{"frame":40,"stamp":4.0,"odometry":[0.1,')
    with caplog.at_level(logging.WARNING):
        store = MapStore(path, PARAMS)
    assert "torn last record" in caplog.text
    assert store.steps == steps[:-1] and path.stat().st_size == size
    store.append(steps[-1])   # the service goes on from there
    store.close()
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert MapStore(path, PARAMS).steps == steps
    assert "torn" not in caplog.text


def test_a_last_record_with_a_bad_checksum_is_skipped_and_cut(tmp_path, caplog):
    path = tmp_path / "map.log"
    steps = square_steps()
    write_store(path, steps)
    lines = path.read_text().splitlines(keepends=True)
    lines[-1] = lines[-1].replace('"template":', '"template":1')   # the record changed, its CRC did not
    path.write_text("".join(lines))
    with caplog.at_level(logging.WARNING):
        store = MapStore(path, PARAMS)
    assert "torn last record" in caplog.text
    assert store.steps == steps[:-1]
    assert path.read_text() == "".join(lines[:-1])
    store.close()


def test_a_damaged_record_in_the_middle_is_an_error_naming_file_and_line(tmp_path):
    path = tmp_path / "map.log"
    write_store(path, square_steps())
    lines = path.read_text().splitlines(keepends=True)
    lines[4] = lines[4].replace('"frame":3', '"frame":7')
    path.write_text("".join(lines))
    with pytest.raises(DataError, match=rf"{path}: line 5: .*damaged"):
        MapStore(path, PARAMS)
    with pytest.raises(DataError, match=rf"{path}: line 5: .*damaged"):
        read_log(path)
    assert path.read_text() == "".join(lines)   # nothing was cut


def test_other_parameters_are_a_clear_error(tmp_path):
    path = tmp_path / "map.log"
    write_store(path, square_steps()[:5])
    with pytest.raises(DataError, match=rf"{path}: .*new_experience_distance.*0\.6.*same parameters"):
        MapStore(path, MapParams(new_experience_distance=1.0))
    with pytest.raises(MapExportError, match=rf"{path}: the map was built with parameters"):
        read_log(path, MapParams(new_experience_distance=1.0))


# --- checkpoints ------------------------------------------------------------------------------
class Every100(CheckpointPolicy):
    """Checkpoints where a test wants them: every 100 frames."""

    def due(self, experience_map: ExperienceMap, steps_since: int) -> bool:
        return steps_since >= 100


EVERY_100 = Every100()


def live_store(path, steps, policy=EVERY_100) -> ExperienceMap:
    """The map as the service builds it: each step journaled, applied, then a checkpoint when due."""
    store, experience_map = MapStore(path, PARAMS, policy), ExperienceMap(PARAMS)
    for step in steps:
        store.append(step)
        step.apply(experience_map)
        if store.checkpoint_due(experience_map):
            store.write_checkpoint(*store.checkpoint(experience_map), {"recent": np.array([step.frame])})
    store.close()
    return experience_map


def same_state(a: ExperienceMap, b: ExperienceMap) -> None:
    """Bit for bit: the whole state, the solver's linearisation point, and every estimate (which
    adds the experiences not yet in the solver to it: compare a map once)."""
    state_a, state_b = a.state(), b.state()
    assert state_a.keys() == state_b.keys()
    for key in state_a:
        assert np.array_equal(state_a[key], state_b[key], equal_nan=True), key
    assert a.decisions == b.decisions and a.residuals == b.residuals
    same_map(a, b)
    assert np.array_equal(a.final_poses(), b.final_poses())


def test_a_map_restored_from_its_checkpoint_and_the_frames_after_it_is_the_map_the_run_had(tmp_path):
    # Two laps: closures accepted at frames 128..135, refused at 200..207, checkpoints after 100 and 200.
    _, steps = two_laps_with_a_look_alike()
    path = tmp_path / "map.log"
    live = live_store(path, steps)
    assert MapStore(path, PARAMS).checkpoints == [100, 200]
    replayed = []
    restored, _, extras = MapStore(path, PARAMS).rebuild(each=lambda step, result: replayed.append(step.frame))
    assert replayed == [step.frame for step in steps[200:]] and extras["recent"].tolist() == [steps[199].frame]
    same_state(restored, live)
    assert restored.closures == {"accepted": 8, "rejected": 8, "unmeasured": 0, "unmatched": 0}
    # The whole journal replayed, rebased where it says, is that map too; without the rebases it is not.
    live = live_store(tmp_path / "again.log", steps)
    full = ExperienceMap(PARAMS)
    replay(full, steps, [100, 200])
    same_state(full, live)
    unrebased = ExperienceMap(PARAMS)
    replay(unrebased, steps, [])
    assert unrebased.decisions == full.decisions
    assert not np.array_equal(unrebased.final_poses(), full.final_poses())


def test_an_earlier_checkpoint_of_the_same_journal_restores_the_same_map(tmp_path):
    # Killed after the journal's second checkpoint record, before its file replaced the first one.
    _, steps = two_laps_with_a_look_alike()
    live_store(tmp_path / "first.log", steps[:150])
    live = live_store(tmp_path / "map.log", steps)
    checkpoint_path(tmp_path / "first.log").replace(checkpoint_path(tmp_path / "map.log"))
    replayed = []
    restored, _, _ = MapStore(tmp_path / "map.log", PARAMS).rebuild(each=lambda step, result: replayed.append(step.frame))
    assert replayed == [step.frame for step in steps[100:]]
    same_state(restored, live)


def damage(path, steps):
    file = checkpoint_path(path)
    file.write_bytes(file.read_bytes()[:len(file.read_bytes()) // 2])


def other_parameters(path, steps):
    file = checkpoint_path(path)
    with np.load(file) as archive:
        arrays = {name: archive[name] for name in archive.files}
    meta = json.loads(str(arrays.pop("meta")))
    meta["params"]["closure_gate"] = 5.0
    write_checkpoint(file, meta, arrays, {})


def another_journals(path, steps):
    live_store(path.with_name("other.log"), square_steps(laps=4.0))   # 128 frames: its checkpoint follows step 100
    checkpoint_path(path.with_name("other.log")).replace(checkpoint_path(path))


def missing(path, steps):
    checkpoint_path(path).unlink()


@pytest.mark.parametrize("spoil, reason", [(damage, "unusable map checkpoint"), (other_parameters, "other map parameters"),
                                           (another_journals, "stale"), (missing, "no map checkpoint")],
                         ids=["damaged", "other parameters", "another journal's", "missing"])
def test_an_unusable_checkpoint_is_named_in_a_warning_and_the_whole_journal_replayed(tmp_path, caplog, spoil, reason):
    _, steps = two_laps_with_a_look_alike()
    path = tmp_path / "map.log"
    live = live_store(path, steps)
    spoil(path, steps)
    replayed = []
    with caplog.at_level(logging.WARNING):
        restored, _, extras = MapStore(path, PARAMS).rebuild(each=lambda step, result: replayed.append(step.frame))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and str(checkpoint_path(path)) in warnings[0] and reason in warnings[0]
    assert f"replaying the whole journal ({len(steps)} frames)" in warnings[0] and "\n" not in warnings[0]
    assert replayed == [step.frame for step in steps] and extras == {}
    same_state(restored, live)


@pytest.mark.parametrize("closure", ["metric", "ratslam"])
def test_a_map_restored_from_its_state_goes_on_bit_for_bit_as_the_rebased_one(closure):
    # Rebased while the robot is between closures (frame 150: the open chain holds the newest
    # experiences) and while lap 2's closures come (frame 130); with RatSLAM's snaps the chains
    # branch where the robot snapped to.
    _, steps = two_laps_with_a_look_alike()
    params = MapParams(new_experience_distance=0.6, closure=closure)
    for split in (130, 150):
        live = ExperienceMap(params)
        for step in steps[:split]:
            step.apply(live)
        restored = ExperienceMap.restore(params, {key: value.copy() for key, value in live.rebase().items()})
        for step in steps[split:]:
            assert step.apply(restored).moved == step.apply(live).moved
        same_state(restored, live)


def test_checkpoints_come_at_the_same_frames_in_two_runs_so_their_journals_are_the_same(tmp_path):
    # Decided on the map's own work (solver updates), not on time.
    _, steps = two_laps_with_a_look_alike()
    policy = CheckpointPolicy(min_steps=20, updates=12)
    live_store(tmp_path / "a.log", steps, policy)
    live_store(tmp_path / "b.log", steps, CheckpointPolicy(min_steps=20, updates=6))
    assert len(MapStore(tmp_path / "a.log", PARAMS).checkpoints) >= 2   # the policy does checkpoint this run
    live_store(tmp_path / "c.log", steps, policy)
    assert (tmp_path / "a.log").read_bytes() == (tmp_path / "c.log").read_bytes()
    assert (tmp_path / "a.log").read_bytes() != (tmp_path / "b.log").read_bytes()


# --- export ---------------------------------------------------------------------------------
def test_export_writes_the_graph_and_the_corrected_trajectory(tmp_path):
    steps = square_steps()
    original = write_store(tmp_path / "map.log", steps)
    result = export_map(tmp_path / "map.log", tmp_path / "graph.json", tmp_path / "map.tum")
    same_map(result.experience_map, original)
    graph = json.loads((tmp_path / "graph.json").read_text())
    assert graph == json.loads(json.dumps(graph_dict(original)))
    assert len(graph["experiences"]) == len(original) and len(graph["links"]) == len(original.links)
    assert [link["loop_closure"] for link in graph["links"]] == [link.loop_closure for link in original.links]
    assert graph["experiences"][3]["x"] == original.final_poses()[3, 0]
    trajectory = read_tum(tmp_path / "map.tum")
    assert trajectory.stamps == pytest.approx([step.stamp for step in steps])
    x, y, heading = trajectory.planar()
    expected = np.array([row[1:] for row in original.trajectory()])
    assert np.column_stack([x, y]) == pytest.approx(expected[:, :2], abs=1e-12)


def test_export_reads_a_torn_log_without_cutting_it(tmp_path, caplog):
    path = tmp_path / "map.log"
    steps = square_steps()
    write_store(path, steps)
    with open(path, "a") as handle:
        handle.write('{"frame":41')
    before = path.read_bytes()
    with caplog.at_level(logging.WARNING):
        map_log = read_log(path)
    assert "torn last record" in caplog.text and map_log.torn_last_record
    assert map_log.steps == steps and map_log.params == PARAMS
    assert path.read_bytes() == before


def test_map_export_command(tmp_path, capsys):
    path = tmp_path / "experience_map.log"
    write_store(path, square_steps(), ExpMapConfig().params())
    assert gridslam(["map", "export", str(path)]) == 0
    assert (tmp_path / "experience_map.graph.json").is_file() and (tmp_path / "experience_map.tum").is_file()
    assert "loop-closure links" in capsys.readouterr().out
    assert gridslam(["map", "export", str(path), "--preset", "nubot", "--tum", str(tmp_path / "x.tum")]) == 1
    assert "the map was built with parameters" in capsys.readouterr().err
    assert gridslam(["map", "export", str(tmp_path / "missing.log")]) == 1
    assert "no such map log" in capsys.readouterr().err


# --- the adapter ----------------------------------------------------------------------------
def messages(steps: list[Step]) -> list[tuple[str, object]]:
    """The expmap service's inputs for `steps`: grid/pose, view/template and loop/closure."""
    out = []
    for step in steps:
        header = Header(seq=step.frame, stamp=Time.from_seconds(step.stamp), frame_id="odom", robot="robot0")
        x, y, heading = step.odometry
        out.append(("pose", GridPose(header=header, pose=planar_pose(x, y, heading), heading=heading,
                                     lattice_shift=(0.0, 0.0), step_length=0.25, integrator="grid",
                                     increment_covariance=list(step.covariance) if step.covariance else None)))
        if step.closure is not None:
            c = step.closure
            out.append(("closure", LoopClosure(
                header=header, frame=step.frame, matched_frame=c.matched_frame, matched_template=c.matched_template,
                votes=7, measurement=c.method, relative_pose=PlanarIncrement(forward=c.forward, left=c.left, yaw=c.yaw),
                covariance=list(c.covariance), inliers=40)))
        out.append(("view", ViewTemplate(header=header, template_id=step.template_id, is_new=False, distance=0.01,
                                         relative_angle=0.0, matched_frame=0, template_count=4,
                                         loop_closure=step.closure is not None)))
    return out


def service(store, published: list | None = None, out=None, **config) -> ExpMapService:
    expmap = ExpMapService(RuntimeConfig(), ExpMapConfig(store=store, new_experience_distance=0.6, out=out, **config))
    expmap._send = lambda topic, message: published.append((topic, message)) if published is not None else None
    return expmap


def deliver(expmap: ExpMapService, inputs) -> None:
    handlers = {"pose": expmap.on_grid_pose, "view": expmap.on_view, "closure": expmap.on_closure}
    for kind, message in inputs:
        handlers[kind](message)


def map_poses(published) -> list:
    return [(m.header.seq, m.pose.position.x, m.pose.position.y, m.heading, m.experience_id)
            for topic, m in published if topic == "map/pose"]


def test_the_same_inputs_in_the_same_order_give_the_same_map(tmp_path):
    steps = square_steps()
    runs = []
    for name in ("a", "b"):
        published = []
        expmap = service(tmp_path / f"{name}.log", published)
        deliver(expmap, messages(steps))
        expmap.teardown()
        runs.append((expmap, published))
    (first, first_published), (second, second_published) = runs
    same_map(first.map, second.map)
    assert map_poses(first_published) == map_poses(second_published)
    assert len(map_poses(first_published)) == len(steps)
    assert (tmp_path / "a.log").read_bytes() == (tmp_path / "b.log").read_bytes()


def test_the_map_does_not_depend_on_how_the_topics_interleave(tmp_path):
    steps = square_steps()
    inputs = messages(steps)
    in_order = service(tmp_path / "a.log")
    deliver(in_order, inputs)
    views_first = service(tmp_path / "b.log")   # every view (and closure) before any pose
    deliver(views_first, [m for m in inputs if m[0] != "pose"] + [m for m in inputs if m[0] == "pose"])
    same_map(in_order.map, views_first.map)


def test_a_killed_service_resumes_from_its_log_to_the_same_map(tmp_path):
    steps = square_steps()
    inputs = messages(steps)
    uninterrupted = service(tmp_path / "a.log")
    deliver(uninterrupted, inputs)
    killed = service(tmp_path / "b.log")
    half = len(inputs) // 2
    deliver(killed, inputs[:half])   # then killed: no teardown, nothing flushed beyond each append
    published = []
    restarted = service(tmp_path / "b.log", published)
    resumed_at = restarted.map.last_frame
    deliver(restarted, inputs)        # the source sends everything again: seen frames are answered, not re-applied
    same_map(uninterrupted.map, restarted.map)
    assert resumed_at is not None and 0 < resumed_at < steps[-1].frame
    assert [seq for seq, *_ in map_poses(published)][-1] == steps[-1].frame


def test_loop_closures_csv_says_which_closures_the_map_kept_and_survives_a_restart(tmp_path):
    frames, steps = two_laps_with_a_look_alike()
    inputs = messages(steps)
    expmap = service(tmp_path / "a.log", out=tmp_path / "a")
    deliver(expmap, inputs)
    rows = list(csv.DictReader(open(tmp_path / "a" / "loop_closures.csv")))
    assert [int(r["frame"]) for r in rows] == list(LAP_CLOSURES) + list(LOOK_ALIKE)
    assert [r["accepted"] for r in rows] == ["true"] * 8 + ["false"] * 8
    assert all(r["measurement"] == "stereo" and r["inliers"] == "40" and float(r["innovation"]) >= 0 for r in rows)
    assert all(float(r["innovation"]) > 3.0 for r in rows[8:])
    assert expmap.extra_counters()["closures_accepted"] == 8 and expmap.extra_counters()["closures_rejected"] == 8
    # Killed half-way (after the journal, before the CSV row: the worst moment) and restarted.
    killed = service(tmp_path / "b.log", out=tmp_path / "b")
    deliver(killed, inputs[:len(inputs) // 2])
    with open(tmp_path / "b" / "loop_closures.csv") as handle:
        torn = handle.readlines()[:-1]
    (tmp_path / "b" / "loop_closures.csv").write_text("".join(torn))
    restarted = service(tmp_path / "b.log", out=tmp_path / "b")
    deliver(restarted, inputs)
    assert (tmp_path / "b" / "loop_closures.csv").read_text() == (tmp_path / "a" / "loop_closures.csv").read_text()


def test_a_service_killed_after_a_checkpoint_restores_it_and_writes_what_the_uninterrupted_one_wrote(tmp_path, caplog):
    frames, steps = two_laps_with_a_look_alike()
    inputs = messages(steps)
    uninterrupted = service(tmp_path / "a.log", out=tmp_path / "a", checkpoint_frames=100, checkpoint_updates=1)
    deliver(uninterrupted, inputs)
    uninterrupted.teardown()
    killed = service(tmp_path / "b.log", out=tmp_path / "b", checkpoint_frames=100, checkpoint_updates=1)
    # Checkpoints come after frame 128 (the first closure's update) and 229. Killed at frame 150:
    # frames 129..150 (closures among them) are replayed, frames 87..128 answered from the checkpoint.
    deliver(killed, [m for m in inputs if m[1].header.seq <= 150])
    killed.writer.join()   # (the kill came after its checkpoint was written)
    published = []
    with caplog.at_level(logging.INFO):
        restarted = service(tmp_path / "b.log", published, out=tmp_path / "b", checkpoint_frames=100, checkpoint_updates=1)
    assert "WARNING" not in caplog.text and "151 frames (checkpoint after 129, 22 replayed)" in caplog.text
    deliver(restarted, inputs)   # everything sent again: the 64 frames up to 150 are answered again, the rest applied
    restarted.teardown()
    assert [seq for seq, *_ in map_poses(published)] == list(range(150 - 63, steps[-1].frame + 1))
    for name in ("a.log", "a/loop_closures.csv"):
        assert (tmp_path / name).read_bytes() == (tmp_path / name.replace("a", "b", 1)).read_bytes(), name
    same_state(restarted.map, uninterrupted.map)


def test_a_snapshot_taken_while_frames_are_applied_is_the_map_of_one_frame(tmp_path):
    steps = square_steps(laps=2.0)
    inputs = messages(steps)
    expmap = service(tmp_path / "live.log")
    snapshots, done = [], threading.Event()

    def query():
        while not done.is_set():
            snapshots.append(expmap.snapshot())

    thread = threading.Thread(target=query)
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-5)   # the threads take turns often: snapshots land in the middle of frames
    thread.start()
    try:
        for message in inputs:
            deliver(expmap, [message])
            time.sleep(1e-4)
    finally:
        done.set()
        thread.join()
        sys.setswitchinterval(interval)
    taken = {m.header.seq: m for m in snapshots if expmap.map.last_frame is not None and m.experiences}
    assert len(taken) >= 5, "too few snapshots during the run to judge"
    # Each snapshot is exactly the map the first frames up to its header's seq make (the journal
    # replayed, rebased at its checkpoints as the service was).
    replayed = ExperienceMap(PARAMS)
    compared = []

    def compare(step, result):
        snapshot = taken.get(step.frame)
        if snapshot is None:
            return
        state = replayed.snapshot()
        assert [(e.x, e.y, e.heading) for e in snapshot.experiences] == [tuple(p) for p in state.poses.tolist()]
        assert [(link.source, link.target, link.accepted) for link in snapshot.links] == \
            [(link.source, link.target, link.accepted) for link in state.links]
        assert all(link.source < len(snapshot.experiences) and link.target < len(snapshot.experiences)
                   for link in snapshot.links)
        compared.append(step.frame)

    replay(replayed, steps, MapStore(tmp_path / "live.log", PARAMS).checkpoints, each=compare)
    assert len(compared) == len(taken)


# --- the offline build on the real NuBot sequence ---------------------------------------------
def test_map_build_on_nubot_closes_the_loop_with_stereo_closures_and_export_replays_it(shared_data, tmp_path, capsys):
    folder = shared_data / "nubot_scene1"
    out = tmp_path / "nubot"
    assert gridslam(["map", "build", "--source", f"stereo:{folder}", "--odometry", str(folder / "libviso2_egomotion.csv"),
                     "--preset", "nubot", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())["summary"]
    assert summary["confirmed_closures"] >= 1 and summary["confirmed_closures_elsewhere"] == 0
    assert 178 <= summary["first_confirmed"]["frame"] <= 204 and summary["first_confirmed"]["matched_frame"] <= 20
    assert summary["closures_accepted"] == summary["confirmed_closures"] and summary["closures_rejected"] == 0
    rows = list(csv.DictReader(open(out / "loop_closures.csv")))
    assert all(r["same_place"] == "True" for r in rows)
    # The robot stops ~5 cm from where it started (the stereo closures measure it); LIBVISO2's
    # dead reckoning ends 0.13 m away. The map ends where the images say.
    assert summary["odometry_end_to_start_m"] > 0.1
    assert 0.02 < summary["corrected_end_to_start_m"] < 0.08
    for name in ("templates_experiences.png", "map_correction.png", "loop_closures.csv", "graph.json"):
        assert (out / name).stat().st_size > 0
    capsys.readouterr()
    assert gridslam(["map", "export", str(out / "experience_map.log"), "--tum", str(tmp_path / "replayed.tum")]) == 0
    built, replayed = read_tum(out / "map.tum"), read_tum(tmp_path / "replayed.tum")
    assert np.array_equal(built.positions, replayed.positions) and np.array_equal(built.stamps, replayed.stamps)
