"""`gridslam health`: list the live services from their liveliness tokens, with their counters."""

from __future__ import annotations

from services.common import health
from services.common.runtime import add_runtime_flags, open_session, runtime_from_args

COLUMNS = ("robot", "service", "instance", "state", "received", "published", "decode_errors", "gaps", "stale", "uptime_s")


def register(subparsers) -> None:
    parser = subparsers.add_parser("health", help="list live services and their counters")
    parser.add_argument("--all-robots", action="store_true", help="every robot on the network, not only --robot")
    parser.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for answers (default 2)")
    add_runtime_flags(parser)
    parser.set_defaults(func=run)


def service_rows(session, robot: str, timeout: float) -> list[dict]:
    """One row per live token, with the counters its status queryable reports (if any)."""
    rows = {key: {"robot": key[0], "service": key[1], "instance": key[2]}
            for key in health.live_services(session, robot, timeout)}
    for status in health.statuses(session, robot, timeout):
        row = rows.get((status.header.robot, status.service, status.instance))
        if row is not None:
            row.update(status.model_dump(include={"state", "received", "published", "decode_errors", "gaps", "stale"}),
                       uptime_s=round(status.uptime, 1))
    return sorted(rows.values(), key=lambda row: (row["robot"], row["service"], row["instance"]))


def run(args) -> int:
    runtime = runtime_from_args(args)
    session = open_session(runtime)
    try:
        rows = service_rows(session, "*" if args.all_robots else runtime.robot, args.timeout)
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
