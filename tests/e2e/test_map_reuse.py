"""A saved map used again, through the real command line: a localisation on it from a start the
first run never began at, and among the campus world's look-alike places; a later session
joined to it; services killed during a localisation; a damaged map refused; a route planned on
it equal to a graph library's shortest path. The saved map is never written."""

import hashlib
import json
import math
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from services.common.layout import SESSION_FRAMES, map_files
from tests.e2e.test_faults import service_pid
from tests.netutil import GRIDSLAM, REPO, endpoint, free_port

CORRIDOR = ["--source", "synthetic:0", "--preset", "synthetic"]


def gridslam(*args: str, check: bool = True, env=None) -> subprocess.CompletedProcess:
    done = subprocess.run(GRIDSLAM + list(args), cwd=REPO, capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0 or not check, done.stderr[-3000:]
    return done


def run(out: Path, *args: str) -> dict:
    gridslam("run", *args, "--listen", endpoint(free_port()), "--out", str(out))
    return json.loads((out / "metrics.json").read_text())


def digest(folder: Path) -> dict[str, str]:
    return {name: hashlib.sha256(path.read_bytes()).hexdigest() for name, path in map_files(folder).items()}


@pytest.fixture(scope="module")
def lap_map(tmp_path_factory) -> Path:
    """Lap 1 of the corridor world, mapped (stereo ego-motion, the synthetic preset)."""
    out = tmp_path_factory.mktemp("map") / "A"
    run(out, *CORRIDOR, "--laps", "1")
    return out


def test_a_localisation_from_a_start_the_map_never_began_at_keeps_to_the_map_and_changes_nothing(lap_map, tmp_path):
    before = digest(lap_map)
    metrics = run(tmp_path / "B", *CORRIDOR, "--laps", "2", "--start", "500", "--n-frames", "240", "--map", str(lap_map),
                  "--localize")
    located = metrics["summary"]["localization"]
    assert located["frames_to_localize"] <= 20, located
    assert located["error_unaligned_m"]["max"] <= 0.10, located    # in the map's frame, no alignment
    assert located["experiences_changed"] == 0 and metrics["summary"]["map_closures"]["accepted_false"] == 0
    assert digest(lap_map) == before                              # the saved map is only read


def test_a_later_session_over_another_part_of_the_route_is_joined_into_one_map(tmp_path):
    first = tmp_path / "A"
    run(first, *CORRIDOR, "--n-frames", "200", "--egomotion", "passthrough")
    metrics = run(tmp_path / "B", *CORRIDOR, "--start", "150", "--n-frames", "200", "--map", str(first),
                  "--egomotion", "passthrough")
    located = metrics["summary"]["localization"]
    assert located["frames_to_localize"] <= 30 and located["error_unaligned_m"]["max"] <= 0.10, located
    assert located["whole_map"]["sessions"] == 2 and located["whole_map"]["error_unaligned_rmse_m"] <= 0.05, located
    graph = tmp_path / "graph.json"
    gridslam("map", "export", str(tmp_path / "B" / "experience_map.log"), "--graph", str(graph), "--tum", str(tmp_path / "B.tum"))
    exported = json.loads(graph.read_text())
    assert exported["connected"] and {e["part"] for e in exported["experiences"]} == {0}
    # The second session's results hold the whole map: the next run starts from it.
    assert min(e["frame"] for e in exported["experiences"]) == 0 and max(e["frame"] for e in exported["experiences"]) > 10**9


def test_the_campus_look_alikes_do_not_place_a_localisation_wrongly(tmp_path):
    # The map of a stretch that passes a corridor (frames 998..1037) and, 69 m away, its copy
    # (frames 1177..1216: walls, floor, ceiling and lamps the same); the localisation starts in the copy.
    campus = ["--source", "synthetic:0", "--preset", "campus", "--egomotion", "passthrough"]
    saved = tmp_path / "A"
    run(saved, *campus, "--start", "990", "--n-frames", "235")
    metrics = run(tmp_path / "B", *campus, "--start", "1177", "--n-frames", "120", "--map", str(saved), "--localize")
    located = metrics["summary"]["localization"]
    assert located["localized_frames"] > 0, located
    assert located["error_unaligned_m"]["max"] <= 2.0, located


def session_frames(journal: Path) -> int:
    """Frames of this run's session in a map journal (numbered from SESSION_FRAMES on)."""
    if not journal.exists():
        return 0
    records = [json.loads(line.rsplit("\t", 1)[0]) for line in journal.read_text().splitlines() if "\t" in line]
    return sum(record.get("frame", 0) >= SESSION_FRAMES for record in records)


def kill_during(out: Path, port: int, args: list[str], kills: dict[str, int]) -> list[str]:
    """Run, killing each service of ``kills`` with SIGKILL once this many frames are in the map's journal."""
    run_process = subprocess.Popen(GRIDSLAM + ["run", *args, "--listen", endpoint(port), "--out", str(out)], cwd=REPO,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    killed = []
    try:
        deadline = time.monotonic() + 300
        while run_process.poll() is None and time.monotonic() < deadline:
            done = session_frames(out / "experience_map.log")
            for name, at in kills.items():
                if name not in killed and done >= at:
                    pid = service_pid(port, name)
                    if pid is not None:
                        os.kill(pid, signal.SIGKILL)
                        killed.append(name)
            time.sleep(0.05)
        _, err = run_process.communicate(timeout=60)
    finally:
        if run_process.poll() is None:
            run_process.kill()
    assert run_process.returncode == 0, err[-3000:]
    return killed


def test_services_killed_during_a_localisation_give_the_poses_of_an_uninterrupted_one(lap_map, tmp_path):
    before = digest(lap_map)
    args = [*CORRIDOR, "--laps", "2", "--start", "500", "--n-frames", "120", "--map", str(lap_map), "--localize",
            "--egomotion", "passthrough"]
    run(tmp_path / "reference", *args)
    killed = kill_during(tmp_path / "faulty", free_port(), args, {"loopclosure": 40, "expmap": 80})
    assert killed == ["loopclosure", "expmap"]
    reference, faulty = ((tmp_path / name / "map_online.tum").read_text() for name in ("reference", "faulty"))
    assert faulty == reference
    assert digest(lap_map) == before


def test_a_damaged_or_missing_saved_map_is_refused_in_one_line(lap_map, tmp_path):
    damaged = tmp_path / "damaged"
    shutil.copytree(lap_map, damaged)
    journal = damaged / "experience_map.log"
    data = bytearray(journal.read_bytes())
    data[len(data) // 2] ^= 0x20
    journal.write_bytes(bytes(data))
    for folder, expected in ((damaged, "experience_map.log: line"), (tmp_path / "nothing", "no such results folder")):
        started = time.monotonic()
        done = gridslam("run", *CORRIDOR, "--map", str(folder), "--localize", "--out", str(tmp_path / "B"), check=False)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 1 and len(lines) == 1 and expected in lines[0], done.stderr[-2000:]
        assert time.monotonic() - started < 10


def test_a_route_is_the_shortest_path_a_graph_library_finds_on_the_exported_graph(lap_map, tmp_path):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    from services.evaluation.trajectory import read_tum

    graph_file = tmp_path / "graph.json"
    gridslam("map", "export", str(lap_map / "experience_map.log"), "--graph", str(graph_file), "--tum", str(tmp_path / "A.tum"))
    graph = json.loads(graph_file.read_text())
    poses = np.array([(e["x"], e["y"]) for e in graph["experiences"]])
    start, goal = poses[3] + 0.05, poses[len(poses) * 2 // 3] - 0.05
    route_file = tmp_path / "route.tum"
    gridslam("map", "route", "--map", str(lap_map), f"--from={start[0]},{start[1]}", f"--to={goal[0]},{goal[1]}",
             "--out", str(route_file))
    route = read_tum(route_file).positions[:, :2]
    links = [link for link in graph["links"] if link["accepted"] and link["source"] != link["target"]]
    costs = coo_matrix(([math.hypot(k["dx"], k["dy"]) for k in links], ([k["source"] for k in links], [k["target"] for k in links])),
                       shape=(len(poses), len(poses))).tocsr()
    first = int(np.argmin(np.hypot(*(poses - start).T)))
    last = int(np.argmin(np.hypot(*(poses - goal).T)))
    distances, previous = dijkstra(costs, directed=False, indices=first, return_predecessors=True)
    path = [last]
    while path[-1] != first:
        path.append(int(previous[path[-1]]))
    expected = poses[path[::-1]]
    assert len(route) == len(expected) and np.allclose(route, expected, atol=1e-9)
    assert (tmp_path / "route.mcap").stat().st_size > 0
