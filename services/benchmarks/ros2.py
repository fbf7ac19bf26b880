"""`gridslam bench ros2`: what the ROS 2 node adds, and whether `--source ros2:` keeps up.

1. Latency: a `gridslam router` and `gridslam service ros2` as processes; this process publishes
   `grid/pose` messages at `--rate` and receives the node's `<ns>/odom` samples (rmw_zenoh keys);
   the time from a gridslam message's put to its ROS 2 sample's arrival, both on this clock.
   That is two Zenoh hops through the router and the node's work: an upper bound of what the
   node adds.
2. Live source: `gridslam service source --source ros2:/bench/image --live-window 0` (no pipeline to
   wait for), fed `--frames` 640×480 mono8 sensor_msgs/Image at 30 frames/s by a ROS 2
   publisher of this process (graph.RosNode); the camera frames it publishes and the drops it
   counts.

Prints a Markdown table.
"""

from __future__ import annotations

import socket
import statistics
import subprocess
import sys
import time

import numpy as np

from services.common.settings import CommandParser


def _start(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "services.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)


def _wait(predicate, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise SystemExit("gridslam bench ros2: timed out waiting for the services")
        time.sleep(0.05)


def _port_open(port: int) -> bool:
    with socket.socket() as sock:
        return sock.connect_ex(("127.0.0.1", port)) == 0


def latency(session, endpoint: str, messages: int, rate: float) -> list[float]:
    from schemas import GridPose, Header, Time
    from services.common import codec, topics
    from services.common.convert import planar_pose
    from services.ros2wire.messages import RosMessages
    from services.ros2wire.rmw_zenoh import topic_key

    ros = RosMessages("jazzy")
    sent: dict[int, float] = {}
    arrived: dict[int, float] = {}

    def on_odom(sample) -> None:
        now = time.perf_counter()
        stamp = ros.store.deserialize_cdr(sample.payload.to_bytes(), "nav_msgs/msg/Odometry").header.stamp
        arrived[stamp.sec * 1000 + stamp.nanosec // 1_000_000] = now

    key = topic_key(0, "/gridslam/odom", "nav_msgs/msg/Odometry", ros.rihs01("nav_msgs/msg/Odometry"))
    subscriber = session.declare_subscriber(key, on_odom)
    publisher = session.declare_publisher(topics.key("robot0", "grid/pose"), encoding=codec.encoding_of(GridPose))
    service = _start(["service", "ros2", "-e", endpoint, "--instance", "bench"])
    try:
        _wait(lambda: any(True for _ in session.liveliness().get("@ros2_lv/0/*/*/*/MP/**", timeout=0.5)), 60)
        time.sleep(1.0)
        for seq in range(messages):
            message = GridPose(header=Header(seq=seq, stamp=Time(sec=seq // 1000, nanosec=(seq % 1000) * 1_000_000)),
                               pose=planar_pose(0.01 * seq, 0.0, 0.0), heading=0.0, lattice_shift=(0.0, 0.0),
                               step_length=0.01, integrator="grid", increment_covariance=[1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-6])
            sent[seq] = time.perf_counter()
            publisher.put(codec.encode(message))
            time.sleep(1.0 / rate)
        time.sleep(1.0)
    finally:
        service.terminate()
        service.wait(timeout=10)
        subscriber.undeclare()
        publisher.undeclare()
    lost = messages - len(arrived)
    if lost:
        print(f"(latency: {lost} of {messages} ROS 2 samples did not arrive)")
    return [1e3 * (arrived[seq] - sent[seq]) for seq in sorted(arrived) if seq in sent]


def live_source(session, endpoint: str, frames: int, fps: float) -> dict:
    from schemas import CameraFrame, ServiceStatus
    from services.common import codec, topics
    from services.ros2wire.graph import RosNode
    from services.ros2wire.messages import RosMessages
    from services.ros2wire.rmw_zenoh import SENSOR_QOS

    ros = RosMessages("jazzy")
    received = []
    statuses = []
    camera = session.declare_subscriber(topics.key("robot0", "camera/frame"),
                                        lambda s: received.append(codec.decode(s.payload.to_bytes(), CameraFrame).header.seq))
    status = session.declare_subscriber(topics.key("robot0", "status/source/bench"),
                                        lambda s: statuses.append(codec.decode(s.payload.to_bytes(), ServiceStatus)))
    source = _start(["service", "source", "-e", endpoint, "--instance", "bench", "--source", "ros2:/bench/image",
                     "--live-window", "0", "--fov", "60", "--stop", str(frames)])
    node = RosNode(session, "bench_camera", "/", hashes=ros.rihs01)
    images = node.publisher("/bench/image", "sensor_msgs/msg/Image", SENSOR_QOS)
    pixels = (np.random.default_rng(0).integers(0, 256, (480, 640))).astype(np.uint8)
    try:
        _wait(lambda: any("%bench%image" in str(r.ok.key_expr) for r in session.liveliness().get(
            "@ros2_lv/0/*/*/*/MS/**", timeout=0.5) if r.ok is not None), 60)
        time.sleep(1.0)
        started = time.perf_counter()
        for index in range(frames):
            due = started + index / fps
            time.sleep(max(0.0, due - time.perf_counter()))
            images.put(ros.mono_image(int(time.time() * 1e9), "camera", pixels))
        source.wait(timeout=30)
        time.sleep(0.5)
    finally:
        if source.poll() is None:
            source.terminate()
            source.wait(timeout=10)
        node.close()
        camera.undeclare()
        status.undeclare()
    last = statuses[-1].extra if statuses else {}
    return {"published": frames, "camera_frames": len(received), "gaps": sum(b - a - 1 for a, b in zip(received, received[1:])),
            "frames_dropped": int(last.get("frames_dropped", -1)), "seconds": frames / fps}


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench ros2", description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=2000, help="grid/pose messages for the latency")
    parser.add_argument("--rate", type=float, default=100.0, help="grid/pose messages per second")
    parser.add_argument("--frames", type=int, default=300, help="640×480 images for the live source")
    parser.add_argument("--fps", type=float, default=30.0, help="images per second")
    args = parser.parse_args(argv)
    from services.common.runtime import RuntimeConfig, open_session

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    router = _start(["router", "--listen", endpoint])
    session = None
    try:
        _wait(lambda: _port_open(port), 15)
        session = open_session(RuntimeConfig(connect=[endpoint], cfg={"timestamping/enabled": "true"}))
        delays = latency(session, endpoint, args.messages, args.rate)
        source = live_source(session, endpoint, args.frames, args.fps)
    finally:
        if session is not None:
            session.close()
        router.terminate()
        router.wait(timeout=10)
    delays.sort()
    p = lambda q: delays[min(len(delays) - 1, int(q * len(delays)))]   # noqa: E731
    print("| measure | value |\n|---|---:|")
    print(f"| grid/pose → /gridslam/odom, samples | {len(delays)} of {args.messages} at {args.rate:g}/s |")
    print(f"| latency p50, ms | {statistics.median(delays):.2f} |")
    print(f"| latency p99, ms | {p(0.99):.2f} |")
    print(f"| latency max, ms | {delays[-1]:.2f} |")
    print(f"| ros2: images published (640×480 mono8, {args.fps:g}/s) | {source['published']} |")
    print(f"| ros2: camera frames out | {source['camera_frames']} |")
    print(f"| ros2: gaps in seq | {source['gaps']} |")
    print(f"| ros2: frames_dropped (source status) | {source['frames_dropped']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
