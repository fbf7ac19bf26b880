"""`gridslam router`: a Zenoh router in Python (no zenohd binary needed)."""

from __future__ import annotations

import logging
import signal
import threading

from services.common import topics
from services.common.runtime import DEFAULT_ROUTER, add_runtime_flags, open_session, runtime_from_args

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    parser = subparsers.add_parser("router", help="run a Zenoh router (default listen tcp/127.0.0.1:7447)")
    add_runtime_flags(parser)
    parser.set_defaults(func=run)


def run(args) -> int:
    runtime = runtime_from_args(args, mode="router", listen=[DEFAULT_ROUTER], connect=[])
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    session = open_session(runtime)
    try:
        token = session.liveliness().declare_token(
            topics.health_key(runtime.robot, "router", str(session.info.zid())))
        print(f"router {session.info.zid()} listening on {', '.join(runtime.listen) or 'default endpoints'}", flush=True)
        stop.wait()
        token.undeclare()
    finally:
        session.close()
    return 0
