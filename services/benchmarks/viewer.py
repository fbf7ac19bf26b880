"""`gridslam bench viewer`: what the viewer costs per message and per browser update.

With `--pipeline FRAMES`, instead: whether a watching viewer slows a running pipeline. A
router and a gridcells service (dead reckoning: the fastest stage there is) run as processes;
FRAMES ego-motion messages are published as fast as back pressure allows (the time until the
last grid pose comes back), then at a steady `--rate` (each frame's latency from publication
to its grid pose), without a viewer, with a viewer, and with a viewer streaming to several
browsers (one of which connects and never reads).

Per topic: decoding a message and handling it (the work the viewer's main thread does for
each sample; its inverse is how many messages per second the viewer can take before it would
push back on the pipeline). Per browser update: building the view under the state lock
(a tail after one frame, and everything, as a newly connected browser gets it) and encoding
it as JSON (outside the lock), with its size; and encoding the images. Medians of wall-clock
and of this thread's CPU time (the machine may be shared: the load average is printed).
"""

from __future__ import annotations

import itertools
import json
import math
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np

import zenoh

from schemas import CameraFrame, EgoMotion, GridActivity, GridPose, Header, MapPose, PlanarIncrement, Time
from services.common import codec, topics
from services.common.convert import image_to_msg, planar_pose
from services.common.runtime import RuntimeConfig, open_session
from services.benchmarks.timing import median_ms
from services.common.settings import CommandParser
from services.viewer.config import ViewerConfig
from services.viewer.service import ViewerService
from services.common.images import encode_camera_jpeg
from services.viewer.state import Cursor, encode_lattice_png


def header(seq: int) -> Header:
    return Header(seq=seq, stamp=Time.from_seconds(seq / 10), robot="robot0")


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench viewer", description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=300, help="timed repetitions per row (default 300)")
    parser.add_argument("--frames", type=int, default=8000, help="frames of history before the view rows (default 8000)")
    parser.add_argument("--experiences", type=int, default=2000, help="experiences in the map (default 2000)")
    parser.add_argument("--pipeline", type=int, metavar="FRAMES", help="measure a running pipeline with and without a viewer instead")
    parser.add_argument("--browsers", type=int, default=4, help="browsers streaming in the --pipeline run (default 4)")
    parser.add_argument("--rate", type=float, default=100.0, help="frames per second of the paced --pipeline runs (default 100)")
    args = parser.parse_args(argv)
    print(f"load average before: {os.getloadavg()[0]:.2f}\n")
    if args.pipeline:
        return pipeline(args.pipeline, args.browsers, args.rate)

    viewer = ViewerService(RuntimeConfig(), ViewerConfig(http="127.0.0.1:0"), "bench")
    rng = np.random.default_rng(0)
    n = args.repeats
    frames = {
        "egomotion": (EgoMotion, viewer.on_egomotion, [EgoMotion(
            header=header(i), increment=PlanarIncrement(forward=0.1, left=0.0, yaw=0.01), quality=1.0,
            estimator="passthrough") for i in range(n)]),
        "grid/pose": (GridPose, viewer.on_grid_pose, [GridPose(
            header=header(i), pose=planar_pose(0.1 * i, 0.0, 0.0), heading=0.0, lattice_shift=(1.0, 0.5),
            step_length=0.1, integrator="grid") for i in range(n)]),
        "map/pose": (MapPose, viewer.on_map_pose, [MapPose(
            header=header(i), pose=planar_pose(0.1 * i, 0.0, 0.0), heading=0.0, experience_id=1) for i in range(n)]),
        "grid/activity 64×64": (GridActivity, viewer.on_grid_activity, [GridActivity(
            header=header(1), image=image_to_msg(rng.integers(0, 256, (64, 64), dtype=np.uint8)), neurons=128,
            max_rate=1.0, lattice_shift=(0.0, 0.0))]),
        "camera/frame 320×240 mono": (CameraFrame, viewer.on_camera_frame, [CameraFrame(
            header=header(1), left=image_to_msg(rng.integers(0, 256, (240, 320), dtype=np.uint8)),
            ground_truth=planar_pose(0.0, 0.0, 0.0))]),
        "camera/frame 1241×376 stereo (KITTI)": (CameraFrame, viewer.on_camera_frame, [CameraFrame(
            header=header(1), left=image_to_msg(rng.integers(0, 256, (376, 1241), dtype=np.uint8)),
            right=image_to_msg(rng.integers(0, 256, (376, 1241), dtype=np.uint8)), ground_truth=planar_pose(0.0, 0.0, 0.0))]),
    }
    print("| message | decode + handle, µs (wall) | CPU µs | messages/s the viewer can take |")
    print("|---|---:|---:|---:|")
    for name, (model, handler, messages) in frames.items():
        payloads = [codec.encode(m) for m in messages]
        cycle = itertools.cycle(payloads)
        wall, cpu = median_ms(lambda: handler(codec.decode(next(cycle), model)), n)
        print(f"| {name} | {1000 * wall:.0f} | {1000 * cpu:.0f} | {1000 / wall:,.0f} |")

    state = viewer.viewer_state
    for i in range(args.frames):
        seq = n + i
        x, y = 0.1 * i, math.sin(i / 50)
        now = time.monotonic()
        state.on_camera_frame(seq, None, np.eye(4), now)
        state.on_egomotion(seq, 0.1, 0.0, 0.001, now)
        state.on_grid_pose(seq, x, y, 0.0, (1.0, 0.0), 0.1, False, "grid", now)
        state.on_map_pose(seq, x, y, 0.0, 1, now)
    state.on_map_snapshot(n + args.frames, [(j, 0.1 * j, math.cos(j)) for j in range(args.experiences)],
                          [(j, j + 1, j % 100 == 0) for j in range(args.experiences - 1)])
    points = sum(len(track.points) for track in state.tracks.values())
    print(f"\nAfter {args.frames} frames ({points} drawn points over {len(state.tracks)} trajectories) "
          f"and {args.experiences} experiences:\n")
    print("| browser update | view under the lock, ms | JSON encoding, ms | bytes |")
    print("|---|---:|---:|---:|")
    seq = n + args.frames

    def tail():
        nonlocal seq
        seq += 1
        now = time.monotonic()
        state.on_grid_pose(seq, 1.0, 1.0, 0.0, (1.0, 0.0), 0.1, False, "grid", now)
        state.on_map_pose(seq, 1.0, 1.0, 0.0, 1, now)
        state.on_egomotion(seq, 0.1, 0.0, 0.0, now)
        return viewer.view(cursor, include_map=False, include_images=False)

    cursor = Cursor()
    viewer.view(cursor)
    rows = {
        "one frame's tail": tail,
        "everything (a browser connects)": lambda: viewer.view(Cursor()),
    }
    for name, build in rows.items():
        view_ms = median_ms(build, min(n, 100))[0]
        sample = build()
        body = json.dumps(sample, separators=(",", ":"))
        json_ms = median_ms(lambda: json.dumps(sample, separators=(",", ":")), min(n, 50))[0]
        print(f"| {name} | {view_ms:.2f} | {json_ms:.2f} | {len(body):,} |")
    experience_map = viewer.view()["map"]
    map_ms = median_ms(lambda: json.dumps(experience_map, separators=(",", ":")), min(n, 50))[0]
    map_bytes = len(json.dumps(experience_map, separators=(",", ":")))
    print(f"| of which the map (encoded once per map change for all browsers) | | {map_ms:.2f} | {map_bytes:,} |")

    camera = rng.integers(0, 256, (240, 320), dtype=np.uint8)
    lattice = rng.integers(0, 256, (64, 64), dtype=np.uint8)
    print("\n| image endpoint | encoding, ms | bytes |")
    print("|---|---:|---:|")
    for name, encode, image in (("camera.jpg 320×240", encode_camera_jpeg, camera), ("lattice.png 64×64", encode_lattice_png, lattice)):
        print(f"| {name} | {median_ms(lambda: encode(image), 50)[0]:.2f} | {len(encode(image)):,} |")
    viewer.close_http()
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")
    return 0


# ---------------------------------------------------------------------- --pipeline
def _gridslam(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "services.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _port_open(port: int) -> bool:
    with socket.socket() as sock:
        return sock.connect_ex(("127.0.0.1", port)) == 0


def _wait(predicate, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise RuntimeError("the pipeline did not come up")
        time.sleep(0.05)


def _stream(url: str, stop: threading.Event, read: bool) -> None:
    try:
        with urllib.request.urlopen(url + "events", timeout=30) as response:
            while not stop.is_set():
                if read:
                    response.readline()
                else:
                    stop.wait(0.1)   # connected, never reading: the server's writes must not block anything else
    except OSError:
        pass


def pipeline(frames: int, browsers: int, rate_hz: float) -> int:
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    processes = [_gridslam("router", "--listen", endpoint)]
    session = None
    try:
        _wait(lambda: _port_open(port))
        processes.append(_gridslam("service", "gridcells", "--integrator", "deadreckoning", "-e", endpoint))
        session = open_session(RuntimeConfig(connect=[endpoint]), threading.Event())
        _wait(lambda: any(r.ok for r in session.liveliness().get(topics.key("robot0", "health/gridcells/*"), timeout=1)))
        arrivals: dict[int, float] = {}
        sent: dict[int, float] = {}
        done = threading.Event()
        expected = 0
        next_seq = 0

        def on_pose(sample):
            seq = codec.decode(sample.payload.to_bytes(), GridPose).header.seq
            arrivals[seq] = time.perf_counter()
            if len(arrivals) == expected:
                done.set()

        subscriber = session.declare_subscriber(topics.key("robot0", "grid/pose"), on_pose)
        publisher = session.declare_publisher(topics.key("robot0", "egomotion"), encoding=codec.encoding_of(EgoMotion),
                                              congestion_control=zenoh.CongestionControl.BLOCK)

        def run_once(count: int, rate: float | None) -> tuple[float, list[float]]:
            """Seconds for `count` frames (as fast as possible when `rate` is None) and each frame's
            latency from publication to its grid pose, ms."""
            nonlocal next_seq, expected
            arrivals.clear()
            sent.clear()
            done.clear()
            expected = count
            seqs = range(next_seq, next_seq + count)
            payloads = [codec.encode(EgoMotion(header=header(seq), increment=PlanarIncrement(
                forward=0.1, left=0.0, yaw=0.001), quality=1.0, estimator="passthrough")) for seq in seqs]
            next_seq += count
            started = time.perf_counter()
            for i, (seq, payload) in enumerate(zip(seqs, payloads)):
                if rate:
                    delay = started + i / rate - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                sent[seq] = time.perf_counter()
                publisher.put(payload)
            if not done.wait(120):
                raise RuntimeError(f"only {len(arrivals)} of {count} grid poses came back")
            return time.perf_counter() - started, [1000 * (arrivals[seq] - sent[seq]) for seq in seqs]

        def measure() -> tuple[float, float, float]:
            """Median seconds of three unpaced runs; median and 95th-percentile latency of a paced run."""
            elapsed = statistics.median(run_once(frames, None)[0] for _ in range(3))
            latencies = sorted(run_once(max(50, int(2 * rate_hz)), rate_hz)[1])
            return elapsed, statistics.median(latencies), latencies[int(0.95 * (len(latencies) - 1))]

        run_once(frames, None)   # warm-up
        rows = [("no viewer", measure())]
        processes.append(_gridslam("service", "viewer", "-e", endpoint, "--http", "127.0.0.1:0"))
        url = processes[-1].stdout.readline().split()[-1]
        _wait(lambda: any(r.ok for r in session.liveliness().get(topics.key("robot0", "health/viewer/*"), timeout=1)))
        rows.append(("viewer, no browser", measure()))
        stop = threading.Event()
        for i in range(browsers):
            threading.Thread(target=_stream, args=(url, stop, i > 0), daemon=True).start()
        time.sleep(1.0)
        rows.append((f"viewer, {browsers} browsers (one never reads)", measure()))
        stop.set()
        time.sleep(1.2)   # the viewer's next status message
        with urllib.request.urlopen(url + "state.json", timeout=10) as response:
            viewer_row = next(row for row in json.loads(response.read())["services"] if row["service"] == "viewer")
        print(f"Unpaced: {frames} egomotion messages through gridcells (dead reckoning), median of three runs. "
              f"Paced: {max(50, int(2 * rate_hz))} messages at {rate_hz:g} Hz, publication to grid pose.\n")
        print("| pipeline | unpaced s | frames/s | ratio to no viewer | paced latency median ms | 95th percentile ms |")
        print("|---|---:|---:|---:|---:|---:|")
        base = rows[0][1][0]
        for name, (elapsed, median, p95) in rows:
            print(f"| {name} | {elapsed:.3f} | {frames / elapsed:,.0f} | {elapsed / base:.2f} | {median:.2f} | {p95:.2f} |")
        print(f"\nThe viewer received {viewer_row['received']} messages and counted {viewer_row['gaps']} missing "
              "(dropped rather than pushing back).")
        subscriber.undeclare()
        publisher.undeclare()
    finally:
        if session is not None:
            session.close()
        for process in processes[::-1]:
            process.terminate()
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")
    return 0
