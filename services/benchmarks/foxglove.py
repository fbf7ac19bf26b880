"""`gridslam bench foxglove`: what the relay in front of the Foxglove server costs, and how long a
client that connects after a run takes to receive it.

1. Relay: `--messages` nav_msgs/Odometry messages (716 bytes of CDR) logged on a foxglove-sdk
   server as fast as it takes them, received by one WebSocket client of this process (the
   `websockets` library), once straight from the SDK's server (`foxglove.sdk.v1`) and once
   through the relay (`foxglove.websocket.v1`); the time from the first message logged to the
   last one received. The client, the server and the relay share this process and its GIL.
2. A finished run: the Foxglove service's history (its default size) fed `--frames` frames of
   four stages' poses (each an Odometry and a /tf message, as the service logs them), then a client connects
   through the relay, subscribes to every channel and is sent the run; the time until it has
   every message, and the bytes the history holds.

Medians of `--repeats` runs, printed as a Markdown table.
"""

from __future__ import annotations

import contextlib
import json
import statistics
import time

from services.common.settings import CommandParser

STAGES = ("egomotion", "gridcells", "map", "groundtruth")


def _client(port: int, subprotocol: str):
    from websockets.sync.client import connect

    return connect(f"ws://127.0.0.1:{port}", subprotocols=[subprotocol], max_size=None, open_timeout=10)


def _subscribe_all(ws) -> int:
    """Subscribe to every advertised channel; how many."""
    while True:
        message = json.loads(ws.recv(timeout=10))
        if message["op"] == "advertise":
            break
    ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": i, "channelId": c["id"]}
                                                             for i, c in enumerate(message["channels"])]}))
    return len(message["channels"])


def _receive(ws, count: int) -> None:
    got = 0
    while got < count:
        if isinstance(ws.recv(timeout=30), bytes):
            got += 1


def relay_cost(messages: int, via_relay: bool) -> float:
    """Seconds from the first message logged to the last one received."""
    import foxglove

    from services.ros2wire.messages import TOPICS, RosMessages
    from services.ros.ws_relay import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL, SubprotocolRelay

    ros = RosMessages()
    topic = "/gridslam/map"
    payload = ros.planar_pose("map", 1, 1.0, 2.0, 0.3)[0][1]
    context = foxglove.Context()
    channel = foxglove.Channel(topic, message_encoding="cdr", context=context, schema=foxglove.Schema(
        name=TOPICS[topic], encoding="ros2msg", data=ros.msgdef(TOPICS[topic]).encode()))
    server = foxglove.start_server(host="127.0.0.1", port=0, context=context, message_backlog_size=messages + 1024)

    class Backend:
        port = server.port

        def close(self) -> None:
            pass

    relay = SubprotocolRelay("127.0.0.1", 0, Backend) if via_relay else None
    try:
        if relay is not None:
            relay.start()
        with _client(relay.port if relay else server.port, LEGACY_SUBPROTOCOL if relay else SDK_SUBPROTOCOL) as ws:
            _subscribe_all(ws)
            time.sleep(0.3)
            started = time.perf_counter()
            for stamp in range(messages):
                channel.log(payload, log_time=stamp)
            _receive(ws, messages)
            return time.perf_counter() - started
    finally:
        if relay is not None:
            relay.stop()
        server.stop()


def finished_run(frames: int) -> tuple[float, int, int]:
    """(seconds until a client has the whole run, messages, bytes held) for `frames` frames."""
    from services.common.runtime import RuntimeConfig
    from services.ros.foxglove import FoxgloveConfig, FoxgloveService
    from services.ros.ws_relay import LEGACY_SUBPROTOCOL

    service = FoxgloveService(RuntimeConfig(), FoxgloveConfig(port=0), "bench")   # the default history
    try:
        service.relay.start()
        for frame in range(frames):
            stamp = 1_000_000_000 + frame * 100_000_000
            for index, stage in enumerate(STAGES):
                service._log(stamp, *service.ros.planar_pose(stage, stamp, 0.1 * frame, 0.01 * index, 0.001 * frame))
        messages = sum(len(kept) for kept in service.history.topics.values())
        held = sum(len(data) for kept in service.history.topics.values() for _, data in kept)
        with contextlib.closing(_client(service.relay.port, LEGACY_SUBPROTOCOL)) as ws:
            started = time.perf_counter()
            _subscribe_all(ws)
            _receive(ws, messages)
            return time.perf_counter() - started, messages, held
    finally:
        service.close_server()


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench foxglove", description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=20000, help="Odometry messages through the relay")
    parser.add_argument("--frames", type=int, default=4541, help="frames of the finished run (KITTI 00 has 4541)")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each measurement (medians)")
    args = parser.parse_args(argv)
    direct = statistics.median(relay_cost(args.messages, False) for _ in range(args.repeats))
    relayed = statistics.median(relay_cost(args.messages, True) for _ in range(args.repeats))
    runs = [finished_run(args.frames) for _ in range(args.repeats)]
    replay = statistics.median(seconds for seconds, _, _ in runs)
    _, messages, held = runs[0]
    print("| measure | value |\n|---|---:|")
    print(f"| {args.messages} Odometry messages straight from the SDK's server (foxglove.sdk.v1), s | {direct:.3f} "
          f"({args.messages / direct:,.0f}/s) |")
    print(f"| the same through the relay (foxglove.websocket.v1), s | {relayed:.3f} ({args.messages / relayed:,.0f}/s) |")
    print(f"| a finished run of {args.frames} frames sent to a client that connects after it: messages | {messages} |")
    print(f"| its history in the Foxglove service, MB | {held / 1e6:.1f} |")
    print(f"| from subscribing to the last message received, s | {replay:.3f} |")
    return 0
