"""A ROS 2 node on an open Zenoh session, in rmw_zenoh's wire format (rmw_zenoh.py): the node's
liveliness token, one publisher or subscription per topic with its own token, and every sample
with its attachment. With `keys="bridge"` the same CDR goes on zenoh-bridge-ros2dds' keys
instead: the plain topic name, no attachment, no rmw_zenoh tokens.

A TRANSIENT_LOCAL publisher is a Zenoh advanced publisher with a cache of `depth` samples and
publisher detection, as rmw_zenoh declares it, so a late ROS 2 subscription (its advanced
subscriber queries the caches of the publishers it detects) gets the last sample; that needs
timestamping in the session's config (`SESSION_CFG`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh
import zenoh.ext

from services.ros2wire import rmw_zenoh
from services.ros2wire.rmw_zenoh import Qos, WireError

log = logging.getLogger(__name__)

# Zenoh settings a process with ROS 2 publishers needs (runtime.cfg): the advanced publisher's cache
# keeps samples by timestamp.
SESSION_CFG = {"timestamping/enabled": "true"}
HEARTBEAT_S = 0.5   # rmw_zenoh's sample-miss heartbeat of RELIABLE, TRANSIENT_LOCAL publishers


@dataclass
class RosEndpoint:
    topic: str          # fully qualified
    msgtype: str
    qos: Qos
    key: str
    token: str | None   # None on bridge keys


class RosPublisher:
    """One topic's publisher: `put(cdr)` sends a sample with its attachment (rmw_zenoh keys)."""

    def __init__(self, endpoint: RosEndpoint, publisher, with_attachment: bool):
        self.endpoint = endpoint
        self._publisher = publisher
        self._gid = rmw_zenoh.gid(endpoint.token) if with_attachment else None
        self._sequence = 0
        self._lock = threading.Lock()
        self.published = 0

    def put(self, cdr: bytes) -> None:
        with self._lock:
            if self._gid is None:
                self._publisher.put(cdr)
            else:
                self._sequence += 1
                self._publisher.put(cdr, attachment=rmw_zenoh.attachment(self._sequence, time.time_ns(), self._gid))
            self.published += 1


class RosNode:
    """A node `name` in `namespace` of ROS domain `domain` on `session` (module docstring)."""

    def __init__(self, session: zenoh.Session, name: str, namespace: str = "/", domain: int = 0,
                 distro: str = rmw_zenoh.DEFAULT_DISTRO, keys: str = "rmw_zenoh", hashes: Callable[[str], str] = None):
        if distro not in rmw_zenoh.DISTROS:
            raise ValueError(f"ROS distro {distro!r} is not one of {', '.join(rmw_zenoh.DISTROS)}")
        if keys not in rmw_zenoh.KEY_STYLES:
            raise ValueError(f"key style {keys!r} is not one of {', '.join(rmw_zenoh.KEY_STYLES)}")
        self.session = session
        self.name, self.namespace, self.domain, self.distro, self.keys = name, namespace, domain, distro, keys
        self._hashes = hashes
        self.zid = str(session.info.zid())
        self.node_id = 0
        self._next_entity = 1
        self._entities: list = []
        self.endpoints: list[RosEndpoint] = []
        if keys == "rmw_zenoh":
            self.token = rmw_zenoh.node_token(domain, self.zid, self.node_id, namespace, name)
            self._entities.append(session.liveliness().declare_token(self.token))
        else:
            self.token = None

    def _endpoint(self, kind: str, topic: str, msgtype: str, qos: Qos) -> RosEndpoint:
        name = rmw_zenoh.fully_qualified(self.namespace, topic)
        if self.keys == "bridge":
            return RosEndpoint(name, msgtype, qos, rmw_zenoh.bridge_key(name), None)
        hash_chunk = rmw_zenoh.type_hash(self.distro, self._hashes(msgtype))
        entity_id, self._next_entity = self._next_entity, self._next_entity + 1
        token = rmw_zenoh.endpoint_token(kind, self.domain, self.zid, self.node_id, entity_id, self.namespace,
                                         self.name, name, msgtype, hash_chunk, qos)
        return RosEndpoint(name, msgtype, qos, rmw_zenoh.topic_key(self.domain, name, msgtype, hash_chunk), token)

    def publisher(self, topic: str, msgtype: str, qos: Qos) -> RosPublisher:
        endpoint = self._endpoint(rmw_zenoh.PUBLISHER, topic, msgtype, qos)
        reliability = zenoh.Reliability.RELIABLE if qos.reliability == rmw_zenoh.RELIABLE else zenoh.Reliability.BEST_EFFORT
        # rmw_zenoh: congestion control DROP, BLOCK only for RELIABLE + KEEP_ALL (a slow subscriber
        # must not stall a KEEP_LAST publisher).
        blocking = qos.reliability == rmw_zenoh.RELIABLE and qos.history == rmw_zenoh.KEEP_ALL
        options = dict(congestion_control=zenoh.CongestionControl.BLOCK if blocking else zenoh.CongestionControl.DROP,
                       reliability=reliability, encoding=zenoh.Encoding.APPLICATION_CDR)
        if qos.durability == rmw_zenoh.TRANSIENT_LOCAL:
            miss = zenoh.ext.MissDetectionConfig(sporadic_heartbeat=HEARTBEAT_S) \
                if qos.reliability == rmw_zenoh.RELIABLE else None
            publisher = zenoh.ext.declare_advanced_publisher(
                self.session, endpoint.key, cache=zenoh.ext.CacheConfig(max_samples=qos.depth), publisher_detection=True,
                sample_miss_detection=miss, **options)
        else:
            publisher = self.session.declare_publisher(endpoint.key, **options)
        self._entities.append(publisher)
        if endpoint.token is not None:
            self._entities.append(self.session.liveliness().declare_token(endpoint.token))
        self.endpoints.append(endpoint)
        return RosPublisher(endpoint, publisher, with_attachment=self.keys == "rmw_zenoh")

    def subscription(self, topic: str, msgtypes: tuple[str, ...], qos: Qos,
                     on_sample: Callable[[str, str, bytes, bytes | None], None]) -> list[RosEndpoint]:
        """Subscribe to `topic` carrying one of `msgtypes`: `on_sample(key, msgtype, cdr, attachment)`
        on a Zenoh thread. On rmw_zenoh keys the type and hash chunks are wildcards (a publisher of
        another distro, or of a type not asked for, is heard and its samples named for what they
        are); one token per type, so the graph sees the subscription. On bridge keys the type
        cannot be read from the key: `msgtypes[0]` is taken."""
        name = rmw_zenoh.fully_qualified(self.namespace, topic)
        if self.keys == "bridge":
            key = rmw_zenoh.bridge_key(name)
            endpoints = [RosEndpoint(name, msgtypes[0], qos, key, None)]
        else:
            key = f"{self.domain}/{name.strip('/')}/*/*"
            endpoints = [self._endpoint(rmw_zenoh.SUBSCRIPTION, topic, msgtype, qos) for msgtype in msgtypes]

        def callback(sample: zenoh.Sample) -> None:
            sample_key = str(sample.key_expr)
            attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
            try:
                msgtype = msgtypes[0] if self.keys == "bridge" else rmw_zenoh.parse_topic_key(sample_key, self.keys).msgtype
            except WireError as error:
                on_sample(sample_key, "", b"", None)   # the consumer counts it
                log.debug("%s", error)
                return
            on_sample(sample_key, msgtype, sample.payload.to_bytes(), attachment)

        self._entities.append(self.session.declare_subscriber(key, callback))
        for endpoint in endpoints:
            if endpoint.token is not None:
                self._entities.append(self.session.liveliness().declare_token(endpoint.token))
        self.endpoints += endpoints
        return endpoints

    def close(self) -> None:
        """Undeclare everything (the session stays open)."""
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except Exception as error:  # already gone with the session
                log.debug("undeclare failed: %s", error)
        self._entities.clear()
