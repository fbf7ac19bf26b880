"""Faults survived by `gridslam run` (issue 7): every service is killed with SIGKILL in turn in
the middle of a run on a recorded sequence; the runner restarts each, the frames in flight are
sent again, and the final map, view templates and loop closures equal those of an
uninterrupted run, each frame in them exactly once."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.netutil import REPO, endpoint, free_port

GRIDSLAM = [sys.executable, "-m", "services.cli"]
# A 6 m × 4 m loop (174 frames a lap): lap 2 confirms closures from about frame 182 on, so the
# loop-closure and map services are killed while closures are being voted and measured.
WORLD = ["--world", "length=6", "--world", "breadth=4"]
FRAMES = 260
# Kill each service once the map holds this many frames.
KILLS = {"source": 30, "egomotion": 60, "gridcells": 90, "loopclosure": 195, "expmap": 225}
# Map checkpoints every 10 frames or more once closures come (20 solver updates), so that expmap
# restarts from one and replays the frames after it (services/expmap/store.py).
ENV = {**os.environ, "GRIDSLAM_EXPMAP_CHECKPOINT_UPDATES": "20", "GRIDSLAM_EXPMAP_CHECKPOINT_FRAMES": "10"}


def run_args(out: Path, port: int, *extra: str) -> list[str]:
    # The passthrough estimator is deterministic (stereo's RANSAC draws differ from run to run).
    return GRIDSLAM + ["run", "--source", "synthetic:0", "--preset", "synthetic", "--egomotion", "passthrough", *WORLD,
                       "--n-frames", str(FRAMES), "--listen", endpoint(port), "--out", str(out), *extra]


def service_pid(port: int, name: str) -> int | None:
    """The pid of `gridslam service NAME` connected to this run's router."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        words = [a.decode(errors="replace") for a in argv]
        if "service" in words and name in words and endpoint(port) in words:
            return int(entry.name)
    return None


def journal(path: Path) -> list[dict]:
    return [json.loads(line.rsplit("\t", 1)[0]) for line in path.read_text().splitlines()]


def frames_in_map(out: Path) -> int:
    try:
        return sum("frame" in record for record in journal(out / "experience_map.log"))
    except (OSError, ValueError):
        return 0


def run_with_kills(tmp_path, kills: dict[str, int], *extra: str) -> tuple[Path, Path]:
    """An uninterrupted run and one whose services `kills` are killed with SIGKILL once the map
    holds so many frames: (reference folder, faulty folder)."""
    reference, faulty = tmp_path / "reference", tmp_path / "faulty"
    done = subprocess.run(run_args(reference, free_port(), *extra), cwd=REPO, capture_output=True, text=True, timeout=300,
                          env=ENV)
    assert done.returncode == 0, done.stderr

    port = free_port()
    run = subprocess.Popen(run_args(faulty, port, *extra), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True, env=ENV)
    killed = []
    try:
        deadline = time.monotonic() + 300
        while run.poll() is None and time.monotonic() < deadline:
            for name, at in kills.items():
                if name not in killed and frames_in_map(faulty) >= at:
                    pid = service_pid(port, name)
                    if pid is not None:
                        os.kill(pid, signal.SIGKILL)
                        killed.append(name)
            time.sleep(0.05)
        out, err = run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 0, err
    assert killed == list(kills), f"killed only {killed}"
    return reference, faulty


def test_kill_each_service_in_turn(tmp_path):
    reference, faulty = run_with_kills(tmp_path, KILLS)

    metrics = json.loads((faulty / "metrics.json").read_text())
    assert {name: metrics["services"][name]["restarts"] for name in KILLS} == dict.fromkeys(KILLS, 1)
    steps = journal(faulty / "experience_map.log")
    assert [step["frame"] for step in steps[1:] if "frame" in step] == list(range(FRAMES))   # each frame once, in order
    assert steps == journal(reference / "experience_map.log")   # checkpoint records at the same places too
    checkpoints = [record["checkpoint"] for record in steps if "checkpoint" in record]
    assert any(n < KILLS["expmap"] for n in checkpoints), checkpoints
    # Restored from it: a missing or unusable checkpoint would have been a warning in its log.
    assert (faulty / "experience_map.log.checkpoint.npz").exists()
    assert "map checkpoint" not in (faulty / "logs" / "expmap.log").read_text()
    assert journal(faulty / "view_templates.log") == journal(reference / "view_templates.log")
    closures = (reference / "loop_closures.csv").read_text()
    closure_frames = [int(line.split(",")[0]) for line in closures.splitlines()[1:]]
    assert min(closure_frames) < KILLS["loopclosure"] and max(closure_frames) > KILLS["expmap"], closure_frames
    assert (faulty / "loop_closures.csv").read_text() == closures
    assert metrics["stages"]["map"]["frames"] == FRAMES and metrics["stages"]["map"]["missing_frames"] == 0


def test_loopclosure_killed_mid_run_resumes_its_bag_of_words_to_the_same_closures(tmp_path):
    """The bag-of-words place recognition: its places, index and votes come back from the
    journal, so the restarted service confirms and measures the same closures."""
    reference, faulty = run_with_kills(tmp_path, {"loopclosure": KILLS["loopclosure"]}, "--place-recognition", "bow")
    assert journal(faulty / "view_templates.log") == journal(reference / "view_templates.log")
    closures = (reference / "loop_closures.csv").read_text()
    closure_frames = [int(line.split(",")[0]) for line in closures.splitlines()[1:]]
    assert min(closure_frames) < KILLS["loopclosure"] < max(closure_frames), closure_frames
    assert (faulty / "loop_closures.csv").read_text() == closures
    assert json.loads((faulty / "metrics.json").read_text())["services"]["loopclosure"]["restarts"] == 1


def test_service_killed_during_start_up_is_restarted(tmp_path):
    """A service killed by a signal before its health token appeared is restarted like one killed
    mid-run (issue 12); only an exit with an error of its own at start-up fails the run."""
    port = free_port()
    args = [arg if arg != str(FRAMES) else "20" for arg in run_args(tmp_path, port)]
    run = subprocess.Popen(args, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while (pid := service_pid(port, "gridcells")) is None and run.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pid is not None, "gridcells never started"
        os.kill(pid, signal.SIGKILL)   # at once: it is still importing, long before its health token
        out, err = run.communicate(timeout=300)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 0, err
    assert "gridcells exited with code -9; restart 1" in err
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["services"]["gridcells"]["restarts"] == 1 and metrics["stages"]["map"]["frames"] == 20
