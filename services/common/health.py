"""Asking the network which services are alive (liveliness tokens) and what their counters
say (status queryables): shared by `gridslam health`, the runner and the viewer's tests."""

from __future__ import annotations

import zenoh

from schemas import ServiceStatus
from services.common import codec, topics


def live_services(session: zenoh.Session, robot: str = "*", timeout: float = 2.0) -> list[tuple[str, str, str]]:
    """(robot, service, instance) of every live health token; `robot` may be a wildcard."""
    found = []
    for reply in session.liveliness().get(f"{topics.PREFIX}/{robot}/health/**", timeout=timeout):
        if reply.ok is not None:
            found.append(topics.parse_health_key(str(reply.ok.key_expr)))
    return found


def statuses(session: zenoh.Session, robot: str = "*", timeout: float = 2.0) -> list[ServiceStatus]:
    """The status every service of `robot` reports on query (replies that do not decode are skipped)."""
    found = []
    for reply in session.get(f"{topics.PREFIX}/{robot}/status/**", timeout=timeout):
        if reply.ok is None:
            continue
        try:
            found.append(codec.decode(reply.ok.payload.to_bytes(), ServiceStatus, str(reply.ok.encoding)))
        except codec.CodecError:
            continue
    return found
