"""Sharded ego-motion (docs/pipeline.md), as real processes over a real router: one egomotion
instance publishes the increments of the estimator run frame after frame (`gridslam odometry`);
`gridslam run --egomotion-instances 3` gives the trajectories of two, frame for frame; an
instance killed mid-run and one added mid-run lose no frame and double none; a second instance
of a stage that keeps state (gridcells, loopclosure, expmap) refuses to start."""

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from services.common.health import live_services, statuses
from tests.e2e.test_faults import GRIDSLAM, frames_in_map, journal, service_pid
from tests.netutil import REPO, client_session, endpoint, free_port, start, start_router, stop, wait_for

pytestmark = pytest.mark.serial   # bit-identical runs while instances come and go: a busy machine's timing is what it tests

# NuBot's last 115 stereo pairs at 640×480 (its 23° turn at frame 153 and the return to the start).
START, FRAMES = 90, 115
TRAJECTORIES = ("egomotion.tum", "gridcells.tum", "map.tum")


def run_args(shared_data: Path, out: Path, port: int, instances: int, *extra: str) -> list[str]:
    return GRIDSLAM + ["run", "--source", f"stereo:{shared_data / 'nubot_scene1'}", "--preset", "nubot", "--egomotion",
                       "stereo", "--start", str(START), "--n-frames", str(FRAMES), "--no-mcap",
                       "--egomotion-instances", str(instances), "--listen", endpoint(port), "--out", str(out), *extra]


def odometry(shared_data: Path, out: Path, *extra: str) -> np.ndarray:
    """`gridslam odometry` on the run's frames: its egomotion.tum (stamp, x, y, z, quaternion)."""
    done = subprocess.run(GRIDSLAM + ["odometry", "--source", f"stereo:{shared_data / 'nubot_scene1'}", "--preset", "nubot",
                                      "--estimator", "stereo", "--start", str(START), "--n-frames", str(FRAMES),
                                      "--out", str(out), *extra], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return np.loadtxt(out / "egomotion.tum")


@pytest.fixture(scope="module")
def two_instances(shared_data, tmp_path_factory):
    out = tmp_path_factory.mktemp("two")
    done = subprocess.run(run_args(shared_data, out, free_port(), 2), cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return out


def assert_same_run(out: Path, reference: Path) -> dict:
    for name in TRAJECTORIES:
        assert (out / name).read_text() == (reference / name).read_text(), name
    steps = journal(out / "experience_map.log")
    assert [step["frame"] for step in steps[1:] if "frame" in step] == list(range(START, START + FRAMES))   # each frame once, in order
    assert steps == journal(reference / "experience_map.log")
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["stages"]["map"]["frames"] == FRAMES and metrics["stages"]["map"]["missing_frames"] == 0
    return metrics


def test_one_instance_publishes_the_estimator_run_frame_after_frame(shared_data, two_instances, tmp_path):
    """The default run measures what `gridslam odometry` measures; several instances publish the
    increments of `gridslam odometry --shard-block 4`, which differ at block starts."""
    done = subprocess.run(run_args(shared_data, tmp_path / "run", free_port(), 1, "--no-mapping"), cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    alone = np.loadtxt(tmp_path / "run" / "egomotion.tum")
    frame_after_frame = odometry(shared_data, tmp_path / "odometry")
    assert alone.shape == frame_after_frame.shape == (FRAMES, 8)
    assert np.abs(alone[:, 1:4] - frame_after_frame[:, 1:4]).max() < 1e-9
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["services"]["egomotion"]["extra"]["estimated_again"] == 0   # no block rebuilt from its primers
    sharded = np.loadtxt(two_instances / "egomotion.tum")
    in_blocks = odometry(shared_data, tmp_path / "blocks", "--shard-block", "4")
    assert np.abs(sharded[:, 1:4] - in_blocks[:, 1:4]).max() < 1e-9
    assert np.abs(sharded[:, 1:4] - alone[:, 1:4]).max() > 1e-3


def test_three_instances_give_the_trajectories_of_two(shared_data, two_instances, tmp_path):
    done = subprocess.run(run_args(shared_data, tmp_path, free_port(), 3), cwd=REPO, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    metrics = assert_same_run(tmp_path, two_instances)
    estimated = {name: metrics["services"][name]["extra"]["estimated"] for name in ("egomotion", "egomotion-2", "egomotion-3")}
    assert all(count >= FRAMES / 6 for count in estimated.values()), estimated   # each took a share
    assert sum(estimated.values()) <= FRAMES + 12, estimated   # a block or two twice at most, while they meet


def estimated_by(session, instance: str) -> float:
    """Frames the egomotion instance has estimated so far, from its status (0 before it answers)."""
    for status in statuses(session, timeout=1.0):
        if status.service == "egomotion" and status.instance == instance:
            return status.extra.get("estimated", 0)
    return 0


def test_an_instance_added_and_one_killed_mid_run(shared_data, two_instances, tmp_path):
    port = free_port()
    run = subprocess.Popen(run_args(shared_data, tmp_path, port, 2), cwd=REPO, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    added = session = None
    try:
        wait_for(lambda: frames_in_map(tmp_path) >= 15 or run.poll() is not None, timeout=120)
        source = service_pid(port, "source")
        assert source is not None and run.poll() is None, "the run ended before an instance could be added"
        # The source pauses while the new instance starts (a second or two), so that the run is
        # still going when it has joined, however busy the machine.
        os.kill(source, signal.SIGSTOP)
        try:
            # Told that instances share the frames (any number above one runs the same blocks).
            added = start(["service", "egomotion", "-e", endpoint(port), "--instance", "added", "--instances", "3",
                           "--preset", "nubot", "--estimator", "stereo"])
            session = client_session(port)
            wait_for(lambda: ("robot0", "egomotion", "added") in live_services(session, timeout=0.5), timeout=60)
        finally:
            os.kill(source, signal.SIGCONT)
        wait_for(lambda: estimated_by(session, "added") > 0 or run.poll() is not None, timeout=120)
        pid = service_pid(port, "egomotion-2")
        assert pid is not None and run.poll() is None, "egomotion-2 is not running"
        killed_at = frames_in_map(tmp_path)
        os.kill(pid, signal.SIGKILL)   # the runner starts it again: it joins with no frame held
        out, err = run.communicate(timeout=300)
    finally:
        if session is not None:
            session.close()
        if run.poll() is None:
            run.kill()
        added_result = stop(added) if added is not None else None
    assert run.returncode == 0, err
    assert added_result is not None and added_result[0] == 0, added_result
    assert killed_at < FRAMES - 10, "killed too late to matter"
    metrics = assert_same_run(tmp_path, two_instances)
    assert metrics["services"]["egomotion-2"]["restarts"] == 1
    assert metrics["services"]["added"]["extra"]["estimated"] > 0


@pytest.mark.parametrize("service", ["gridcells", "loopclosure", "expmap"])
def test_a_second_instance_of_a_stateful_stage_refuses_to_start(service, tmp_path):
    port = free_port()
    router = start_router(port)
    first = start(["service", service, "-e", endpoint(port), "--instance", "first"], cwd=tmp_path)
    try:
        session = client_session(port)
        try:
            wait_for(lambda: ("robot0", service, "first") in live_services(session, timeout=0.5), timeout=60)
        finally:
            session.close()
        started = time.monotonic()
        second = subprocess.run(GRIDSLAM + ["service", service, "-e", endpoint(port), "--instance", "second"],
                                cwd=tmp_path, capture_output=True, text=True, timeout=60)
        assert second.returncode == 1
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and "already running (instance first)" in lines[0] and service in lines[0], second.stderr
        assert time.monotonic() - started < 30
        assert first.poll() is None   # the first one goes on
    finally:
        stop(first)
        stop(router)
