"""`gridslam echo KEYEXPR`: print decoded messages one per line as JSON (like `ros2 topic echo`)."""

from __future__ import annotations

import json
import signal
import sys
import threading

import zenoh

from services.common import codec, topics
from services.common.runtime import add_runtime_flags, open_session, runtime_from_args


def register(subparsers) -> None:
    parser = subparsers.add_parser("echo", help="print the messages on a key expression as JSON lines")
    parser.add_argument("keyexpr", metavar="KEYEXPR",
                        help="a full key expression (gridslam/@v1/robot0/grid/pose, wildcards allowed) or a topic (grid/pose)")
    parser.add_argument("-n", "--count", type=int, help="exit after this many messages")
    add_runtime_flags(parser)
    parser.set_defaults(func=run)


def printable(value):
    """JSON-ready copy of a model dump: raw bytes (image pixels) are shown by their size."""
    if isinstance(value, bytes):
        return f"<{len(value)} bytes>"
    if isinstance(value, dict):
        return {k: printable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [printable(v) for v in value]
    return value


def to_line(sample: zenoh.Sample) -> str:
    key = str(sample.key_expr)
    try:
        message = codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding))
    except codec.CodecError as error:
        return json.dumps({"key": key, "error": str(error)})
    return json.dumps({"key": key, "kind": message.KIND, "message": printable(message.model_dump())})


def run(args) -> int:
    runtime = runtime_from_args(args)
    keyexpr = args.keyexpr if args.keyexpr.startswith(topics.PREFIX) else topics.key(runtime.robot, args.keyexpr)
    done = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: done.set())
    printed = 0
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal printed
        line = to_line(sample)
        with lock:
            if done.is_set():
                return
            print(line, flush=True)
            printed += 1
            if args.count is not None and printed >= args.count:
                done.set()

    session = open_session(runtime)
    try:
        subscriber = session.declare_subscriber(keyexpr, on_sample)
        print(f"listening on {keyexpr}", file=sys.stderr, flush=True)
        done.wait()
        subscriber.undeclare()
    finally:
        session.close()
    return 0
