"""The disk (issue 7): a read-only results folder, a disk that fills during `gridslam run`, and the
experience map's journal hitting a file size limit. Each ends with one clear line and exit
code 1, and the map already written reloads intact: every frame once, in order."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import time
from pathlib import Path

import pytest
import zenoh

from services.common import codec, topics
from services.expmap.export import read_log
from tests.e2e.test_reliability_fuzz import grid_pose, view
from tests.netutil import GRIDSLAM, REPO, client_session, endpoint, free_port, start_router, stop, wait_for


def mount_tmpfs(folder: Path, options: str) -> None:
    """A small tmpfs at `folder`, or a skip where this process may not mount (not root, no CAP_SYS_ADMIN)."""
    folder.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")


@pytest.fixture
def mounts():
    mounted: list[Path] = []
    yield lambda folder, options: (mount_tmpfs(folder, options), mounted.append(folder))
    for folder in mounted:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def one_error_line(done: subprocess.CompletedProcess, command: str) -> str:
    """The run's error: exit code 1 and a last stderr line `gridslam COMMAND: error: ...`."""
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and lines and lines[-1].startswith(f"gridslam {command}: error: "), done.stderr[-3000:]
    return lines[-1]


def run_args(out: Path | None, *extra: str) -> list[str]:
    return GRIDSLAM + ["run", "--source", "synthetic:0", "--preset", "synthetic", "--egomotion", "passthrough",
                       "--integrator", "deadreckoning", "--listen", endpoint(free_port()),
                       *(["--out", str(out)] if out else []), *extra]


def test_read_only_results_folder_is_one_line(tmp_path, mounts):
    folder = tmp_path / "read-only"
    if os.geteuid() == 0:
        mounts(folder, "ro,size=64k")   # root writes through file modes: only a read-only mount stops it
    else:
        folder.mkdir()
        folder.chmod(0o555)
    # --out there, or the default results/ of a run started there
    for out, cwd, named in ((folder / "out", REPO, str(folder / "out")), (None, folder, "results")):
        done = subprocess.run(run_args(out, "--n-frames", "5"), cwd=cwd, capture_output=True, text=True, timeout=120,
                              env={**os.environ, "PYTHONPATH": str(REPO)})
        line = one_error_line(done, "run")
        assert f"error: {named}: " in line and ("Read-only file system" in line or "Permission denied" in line), line
        assert len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_disk_full_during_a_run_is_one_line_and_the_map_reloads(tmp_path, mounts):
    disk = tmp_path / "disk"
    mounts(disk, "size=160k")
    out = disk / "out"
    started = time.monotonic()
    done = subprocess.run(run_args(out, "--n-frames", "1000"), cwd=REPO, capture_output=True, text=True, timeout=300)
    elapsed = time.monotonic() - started
    line = one_error_line(done, "run")
    print(f"after {elapsed:.1f} s: {line}")
    # The service whose file filled first is named, with the file; the run did not wait out its
    # stall timeout (60 s) but stopped after a few restarts that could not help.
    assert "No space left on device" in line and str(out) in line and "exited 4 times" in line, line
    assert elapsed < 60, elapsed
    log = read_log(out / "experience_map.log")
    frames = [step.frame for step in log.steps]
    print(f"the map log holds frames 0 to {frames[-1]}, each once")
    assert len(frames) >= 20 and frames == list(range(len(frames)))
    export = subprocess.run(GRIDSLAM + ["map", "export", str(out / "experience_map.log"), "--graph", str(tmp_path / "map.json"),
                                        "--tum", str(tmp_path / "map.tum")], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert export.returncode == 0, export.stderr
    graph = json.loads((tmp_path / "map.json").read_text())
    rows = [row for row in (tmp_path / "map.tum").read_text().splitlines() if not row.startswith("#")]
    assert graph["experiences"] and len(rows) == len(frames)


def limit_file_size(limit: int):
    def apply() -> None:   # in the child, before exec: files it writes stop growing at `limit` bytes (EFBIG)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def test_map_journal_that_cannot_grow_stops_expmap_and_keeps_what_it_wrote(tmp_path):
    """The same as a full disk for the expmap service alone, without root: RLIMIT_FSIZE on its journal."""
    port = free_port()
    router = start_router(port)
    store = tmp_path / "experience_map.log"
    # (Zenoh's shared-memory segment is a file too: the limit would refuse it, so it is off here.)
    expmap = subprocess.Popen(GRIDSLAM + ["service", "expmap", "--preset", "synthetic", "--store", str(store), "-e",
                                          endpoint(port), "--instance", "disk", "--cfg", "transport/shared_memory/enabled:false"],
                              cwd=REPO, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, preexec_fn=limit_file_size(8192))
    session = client_session(port)
    published: list[int] = []
    subscriber = session.declare_subscriber(topics.key("robot0", "map/pose"), lambda sample: published.append(
        codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding)).header.seq))
    try:
        wait_for(lambda: any(r.ok for r in session.liveliness().get(topics.health_key("robot0", "expmap", "disk"), timeout=1)),
                 timeout=60)
        for seq in range(200):   # about 140 bytes a frame: the limit is reached near frame 55
            if expmap.poll() is not None:
                break
            for topic, message in (("grid/pose", grid_pose(seq, "robot0", 0.1 * seq, 0.0, 0.0)),
                                   ("view/template", view(seq, "robot0", seq // 10, seq % 10 == 0, seq - seq % 10))):
                session.put(topics.key("robot0", topic), codec.encode(message), encoding=codec.encoding_of(message),
                            congestion_control=zenoh.CongestionControl.BLOCK)
            time.sleep(0.005)
        code = expmap.wait(timeout=30)
        err = expmap.stderr.read()
    finally:
        subscriber.undeclare()
        session.close()
        stop(expmap)
        stop(router)
    lines = err.strip().splitlines()
    assert code == 1 and lines[-1] == f"gridslam service: error: {store}: cannot append (File too large)", err[-3000:]
    log = read_log(store)
    frames = [step.frame for step in log.steps]
    assert 20 <= len(frames) < 200 and frames == list(range(len(frames)))
    assert set(published) <= set(frames)   # every pose it published was on disk first
    assert store.stat().st_size <= 8192
