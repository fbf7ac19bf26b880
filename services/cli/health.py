"""`gridslam health`: list the live services from their liveliness tokens, with their counters."""

from __future__ import annotations

from services.common import codec, topics
from services.common.runtime import add_runtime_flags, open_session, runtime_from_args

COLUMNS = ("robot", "service", "instance", "state", "received", "published", "decode_errors", "gaps", "stale", "uptime_s")


def register(subparsers) -> None:
    parser = subparsers.add_parser("health", help="list live services and their counters")
    parser.add_argument("--all-robots", action="store_true", help="every robot on the network, not only --robot")
    parser.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for answers (default 2)")
    add_runtime_flags(parser)
    parser.set_defaults(func=run)


def live_services(session, robot: str, timeout: float) -> list[dict]:
    """One row per live token, with the counters its status queryable reports (if any)."""
    rows: dict[tuple[str, str, str], dict] = {}
    for reply in session.liveliness().get(f"{topics.PREFIX}/{robot}/health/**", timeout=timeout):
        if reply.ok is not None:
            robot_name, service, instance = topics.parse_health_key(str(reply.ok.key_expr))
            rows[(robot_name, service, instance)] = {"robot": robot_name, "service": service, "instance": instance}
    for reply in session.get(f"{topics.PREFIX}/{robot}/status/**", timeout=timeout):
        if reply.ok is None:
            continue
        try:
            status = codec.decode(reply.ok.payload.to_bytes(), encoding=str(reply.ok.encoding))
        except codec.CodecError:
            continue
        row = rows.get((status.header.robot, status.service, status.instance))
        if row is not None:
            row.update(status.model_dump(include={"state", "received", "published", "decode_errors", "gaps", "stale"}),
                       uptime_s=round(status.uptime, 1))
    return sorted(rows.values(), key=lambda row: (row["robot"], row["service"], row["instance"]))


def run(args) -> int:
    runtime = runtime_from_args(args)
    session = open_session(runtime)
    try:
        rows = live_services(session, "*" if args.all_robots else runtime.robot, args.timeout)
    finally:
        session.close()
    if not rows:
        print("no live services")
        return 0
    table = [COLUMNS] + [tuple(str(row.get(column, "-")) for column in COLUMNS) for row in rows]
    widths = [max(len(line[i]) for line in table) for i in range(len(COLUMNS))]
    for line in table:
        print("  ".join(cell.ljust(width) for cell, width in zip(line, widths)).rstrip())
    return 0
