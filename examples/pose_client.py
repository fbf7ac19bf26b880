"""A gridslam client that needs only `eclipse-zenoh` and `msgpack` (no gridslam import).

It subscribes to the grid-cell odometry and the map-corrected pose of one robot and prints
one line per message: topic, frame index, x, y (metres) and heading (radians).

    pip install eclipse-zenoh msgpack
    python pose_client.py --connect tcp/127.0.0.1:7447 --robot robot0
"""

import argparse
import json
import threading

import msgpack
import zenoh


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447", help="router endpoint")
    parser.add_argument("--robot", default="robot0", help="robot name")
    parser.add_argument("--count", type=int, default=0, help="exit after this many messages (0: never)")
    args = parser.parse_args()

    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([args.connect]))
    config.insert_json5("scouting/multicast/enabled", "false")

    done = threading.Event()
    lock = threading.Lock()
    seen = 0

    def on_pose(sample: zenoh.Sample) -> None:
        nonlocal seen
        # Every gridslam message is msgpack of a map; the encoding names its schema, e.g.
        # "application/msgpack;MapPose". Field layouts mirror ROS 2 (header, pose.position, ...).
        message = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        topic = str(sample.key_expr).split("/", 3)[3]
        position = message["pose"]["position"]
        with lock:
            if done.is_set():
                return
            print(f"{topic} seq={message['header']['seq']} x={position['x']:.3f} y={position['y']:.3f} "
                  f"heading={message['heading']:.3f}", flush=True)
            seen += 1
            if args.count and seen >= args.count:
                done.set()

    session = zenoh.open(config)
    try:
        prefix = f"gridslam/@v1/{args.robot}"
        subscribers = [session.declare_subscriber(f"{prefix}/{topic}", on_pose) for topic in ("map/pose", "grid/pose")]
        try:
            done.wait()
        except KeyboardInterrupt:
            pass
        for subscriber in subscribers:
            subscriber.undeclare()
    finally:
        session.close()


if __name__ == "__main__":
    main()
