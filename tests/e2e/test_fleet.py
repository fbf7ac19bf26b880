"""A fleet from the real command line (docs/fleet.md): two robots that start at different places
on the corridor world and on the campus, meet, and end in one frame; the fleet map killed with
SIGKILL mid-run and restarted by the runner, catching up without fusing anything twice."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

from services.common.journal import read_records
from tests.netutil import endpoint, free_port, start, stop, wait_for


def fleetmap_pid(out: Path) -> int | None:
    """The fleet map process this test's run started (its journal is in `out`)."""
    store = str(out / "fleet" / "fleet_map.log")
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                command = (entry / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"fleetmap" in command and store.encode() in command:
                return int(entry.name)
    return None


def journal_inputs(out: Path) -> list[dict]:
    return [r for r in read_records(out / "fleet" / "fleet_map.log")[0][1:] if "checkpoint" not in r]


def test_two_robots_meet_and_the_fleet_map_survives_a_kill(tmp_path):
    out = tmp_path / "fleet"
    run = start(["run", "--fleet", "--source", "synthetic:0", "--preset", "synthetic", "--egomotion", "passthrough",
                 "--n-frames", "220", "--robot-start", "0", "--robot-start", "100", "--listen", endpoint(free_port()),
                 "--out", str(out)])
    try:
        # Once the fleet map has taken some of both robots' maps, kill it; the runner starts it again.
        wait_for(lambda: (out / "fleet" / "fleet_map.log").exists() and len(journal_inputs(out)) > 40
                 or run.poll() is not None, timeout=120, period=0.5)
        pid = fleetmap_pid(out)
        assert pid is not None and run.poll() is None
        os.kill(pid, signal.SIGKILL)
        stdout, stderr = run.communicate(timeout=300)
        code = run.returncode
    finally:
        if run.poll() is None:
            stop(run)
    assert code == 0, stderr[-2000:]
    fleet = json.loads((out / "metrics.json").read_text())["fleet"]
    assert fleet["joined_at"]["a"] == 0 and fleet["joined_at"]["b"] is not None
    assert fleet["inter_robot_closures_accepted"] >= 20 and fleet["inter_robot_closures_accepted_false"] == 0
    assert fleet["ate_m"]["b"] < 0.1 and fleet["online_error_after_join_m"]["b"]["max"] < 0.3
    # a robot joining mid-run: placed soon after it first comes to a place the other saw
    assert fleet["frames_to_join"]["b"] is not None and fleet["frames_to_join"]["b"] <= 20
    assert fleet["fleetmap_restarts"] == 1   # and it resumed from its journal: every input once, below
    # nothing fused twice: each closure, and each part of a robot's map, once in the journal
    closures = [(r["closure"]["robot"], r["closure"]["index"]) for r in journal_inputs(out) if "closure" in r]
    assert len(closures) == len(set(closures)) == fleet["inter_robot_closures_confirmed"]
    experiences = [(r["map"], e[0]) for r in journal_inputs(out) if "map" in r for e in r["experiences"]]
    assert len(experiences) == len(set(experiences))
    for robot in ("a", "b"):
        assert (out / "fleet" / f"{robot}.tum").stat().st_size > 0
        assert (out / "fleet" / f"{robot}.groundtruth.tum").stat().st_size > 0
