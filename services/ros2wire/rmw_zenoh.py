"""rmw_zenoh's wire format, as strings and bytes: what a ROS 2 node started with
`RMW_IMPLEMENTATION=rmw_zenoh_cpp` expects to find on Zenoh (docs/ecosystem.md, "ROS 2 live").
Pure: names and numbers in, key expressions, liveliness tokens and attachments out; the
session side is graph.py.

Read from rmw_zenoh's docs/design.md and its sources (`liveliness_utils.cpp`, `qos.cpp`,
`attachment_helpers.cpp`, `type_support_common.cpp`) on the humble 0.1.9, jazzy 0.2.10,
kilted 0.6.7 and rolling 0.12.0 releases, which agree on everything below:

- data key `<domain>/<fully qualified name without its leading />/<pkg>::msg::dds_::<Type>_/<type hash>`,
  the type hash RIHS01 (REP-2016) from Jazzy on, the literal `TypeHashNotSupported` on Humble;
- liveliness tokens `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS|SS|SC>/<enclave>/
  <namespace>/<node>[/<topic>/<type>/<hash>/<qos>]`, every `/` of a name written `%` (so the
  root namespace and enclave `/` are `%`); a node's entity id is its node id;
- QoS `reliability:durability:history,depth:deadline s,ns:lifespan s,ns:liveliness,lease s,ns`,
  each field empty where it equals rmw_zenoh's default (RELIABLE, VOLATILE, KEEP_LAST 42,
  infinite durations, AUTOMATIC liveliness), enums as rmw's numbers;
- an attachment on every sample, written with Zenoh's serializer: int64 sequence number (from
  1), int64 source timestamp (ns since the epoch), the publisher's 16-byte GID as a sequence
  (a 1-byte length, 16) — 33 bytes; a ROS 2 subscription drops a sample without it;
- the GID is XXH3-128 of the entity's liveliness token (low 64 bits first, little-endian).

The zenoh-bridge-ros2dds bridge, for graphs that run DDS, puts the same CDR on the plain topic
name (`bridge_key`), without an attachment.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from services.common.errors import DataError
from services.common.settings import setting

ADMIN_SPACE = "@ros2_lv"
DISTROS = ("jazzy", "kilted", "rolling", "humble")
DEFAULT_DISTRO = "jazzy"
KEY_STYLES = ("rmw_zenoh", "bridge")
TYPE_HASH_NOT_SUPPORTED = "TypeHashNotSupported"   # Humble's rmw_zenoh: no type hashes before Iron
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE

# rmw's enums (rmw/types.h).
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
AUTOMATIC = 1
DURATION_INFINITE = (9223372036, 854775807)   # RMW_DURATION_INFINITE, s and ns


class WireError(DataError):
    """A sample or token that is not rmw_zenoh's (the message says what is wrong)."""


@dataclass(frozen=True)
class Qos:
    """The QoS of an endpoint as rmw_zenoh resolves it (durations: (s, ns))."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 42
    deadline: tuple[int, int] = DURATION_INFINITE
    lifespan: tuple[int, int] = DURATION_INFINITE
    liveliness: int = AUTOMATIC
    lease: tuple[int, int] = DURATION_INFINITE

    def encode(self) -> str:
        """The token's QoS chunk (rmw_zenoh's qos_to_keyexpr)."""
        default = RMW_ZENOH_DEFAULT_QOS

        def field(name: str) -> str:
            value = getattr(self, name)
            return "" if value == getattr(default, name) else str(value)

        def duration(name: str) -> str:
            value, base = getattr(self, name), getattr(default, name)
            return ",".join("" if v == b else str(v) for v, b in zip(value, base))

        return ":".join([field("reliability"), field("durability"), f"{field('history')},{field('depth')}",
                         duration("deadline"), duration("lifespan"), f"{field('liveliness')},{duration('lease')}"])


RMW_ZENOH_DEFAULT_QOS = Qos()
# What gridslam offers: sensor data best effort (depth 5), the rest reliable; a latched topic
# (TRANSIENT_LOCAL, depth 1) is served to late subscribers from the publisher's cache.
SENSOR_QOS = Qos(reliability=BEST_EFFORT, depth=5)
RELIABLE_QOS = Qos(depth=10)
TF_QOS = Qos(depth=100)                      # tf2's listener: reliable, volatile, depth 100
LATCHED_QOS = Qos(durability=TRANSIENT_LOCAL, depth=1)


def dds_type_name(msgtype: str) -> str:
    """`nav_msgs/msg/Odometry` → `nav_msgs::msg::dds_::Odometry_` (rmw's type name in CDR)."""
    package, kind, name = _split_type(msgtype)
    return f"{package}::{kind}::dds_::{name}_"


def ros_type_name(dds_type: str) -> str:
    """`nav_msgs::msg::dds_::Odometry_` → `nav_msgs/msg/Odometry`; WireError for anything else."""
    parts = dds_type.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_") or len(parts[3]) < 2:
        raise WireError(f"{dds_type!r} is not a ROS 2 DDS type name (pkg::msg::dds_::Type_)")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def _split_type(msgtype: str) -> tuple[str, str, str]:
    parts = msgtype.split("/")
    if len(parts) != 3 or not all(parts):
        raise WireError(f"{msgtype!r} is not a ROS 2 type name (pkg/msg/Type)")
    return parts[0], parts[1], parts[2]


def fully_qualified(namespace: str, name: str) -> str:
    """A topic name as ROS 2 resolves it in a node's namespace: absolute names stay, relative
    ones go under the namespace (`/gridslam` + `odom` → `/gridslam/odom`)."""
    if name.startswith("/"):
        return name
    return f"{namespace.rstrip('/')}/{name}"


def normalise_namespace(namespace: str) -> str:
    """A ROS 2 namespace: absolute, without a trailing slash (the root is `/`); WireError when
    it has an empty part or characters ROS 2 does not allow."""
    text = "/" + namespace.strip("/")
    parts = text.strip("/").split("/") if text != "/" else []
    for part in parts:
        if not part or not all(c.isalnum() or c == "_" for c in part) or part[0].isdigit():
            raise WireError(f"ROS namespace {namespace!r}: each part must be letters, digits and _ "
                            "and must not start with a digit")
    return text


def mangle(name: str) -> str:
    """A name inside a liveliness token: every `/` written `%` (the root `/` is `%`)."""
    return name.replace("/", "%")


def type_hash(distro: str, rihs01: str) -> str:
    """The hash chunk of keys and tokens: RIHS01 from Jazzy on, Humble's literal before."""
    return TYPE_HASH_NOT_SUPPORTED if distro == "humble" else rihs01


def topic_key(domain: int, topic: str, msgtype: str, hash_chunk: str) -> str:
    """The data key expression of a topic (`topic` fully qualified)."""
    return f"{domain}/{topic.strip('/')}/{dds_type_name(msgtype)}/{hash_chunk}"


def bridge_key(topic: str) -> str:
    """zenoh-bridge-ros2dds' key of a topic (its namespace left at `/`): the name without its leading /."""
    return topic.strip("/")


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str, enclave: str = "/") -> str:
    """The liveliness token that makes a node appear in the graph."""
    return "/".join([ADMIN_SPACE, str(domain), zid, str(node_id), str(node_id), NODE, mangle(enclave),
                     mangle(namespace), mangle(node)])


def endpoint_token(kind: str, domain: int, zid: str, node_id: int, entity_id: int, namespace: str, node: str,
                   topic: str, msgtype: str, hash_chunk: str, qos: Qos, enclave: str = "/") -> str:
    """The liveliness token of a publisher (MP) or subscription (MS) of a node."""
    if kind not in (PUBLISHER, SUBSCRIPTION):
        raise ValueError(f"endpoint kind {kind!r} is not {PUBLISHER} or {SUBSCRIPTION}")
    return "/".join([ADMIN_SPACE, str(domain), zid, str(node_id), str(entity_id), kind, mangle(enclave),
                     mangle(namespace), mangle(node), mangle(topic), dds_type_name(msgtype), mangle(hash_chunk),
                     qos.encode()])


def gid(token: str) -> bytes:
    """An entity's GID as rmw_zenoh makes it: XXH3-128 of its token, low 64 bits then high, little-endian."""
    import xxhash   # (in the extra `ros`)

    return xxhash.xxh3_128_digest(token.encode())[::-1]   # the digest is big-endian (high, low)


def attachment(sequence: int, source_timestamp_ns: int, publisher_gid: bytes) -> bytes:
    """The 33-byte attachment of a sample, as Zenoh's serializer writes (int64, int64, uint8 sequence)."""
    if len(publisher_gid) != GID_SIZE:
        raise ValueError(f"a GID has {GID_SIZE} bytes, not {len(publisher_gid)}")
    return struct.pack("<qqB", sequence, source_timestamp_ns, GID_SIZE) + bytes(publisher_gid)


def parse_attachment(data: bytes | None) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of a sample's attachment; WireError when it
    is missing or is not rmw_zenoh's."""
    if data is None:
        raise WireError("a sample without rmw_zenoh's attachment (sequence number, timestamp, GID)")
    if len(data) != ATTACHMENT_SIZE or data[16] != GID_SIZE:
        raise WireError(f"an attachment of {len(data)} bytes is not rmw_zenoh's ({ATTACHMENT_SIZE}: int64, int64, "
                        f"a {GID_SIZE}-byte GID)")
    sequence, stamp = struct.unpack_from("<qq", data)
    return sequence, stamp, bytes(data[17:])


@dataclass(frozen=True)
class TopicKey:
    """What a data key says: the topic (fully qualified), its ROS type (None for a bridge key) and hash."""

    topic: str
    msgtype: str | None
    hash_chunk: str | None


def parse_topic_key(key: str, style: str) -> TopicKey:
    """A data key read back (`style` rmw_zenoh: domain, name, type, hash; bridge: the name)."""
    if style == "bridge":
        return TopicKey("/" + key.strip("/"), None, None)
    parts = key.split("/")
    if len(parts) < 4 or not parts[0].isdigit():
        raise WireError(f"key {key!r} is not rmw_zenoh's <domain>/<topic>/<type>/<hash>")
    return TopicKey("/" + "/".join(parts[1:-2]), ros_type_name(parts[-2]), parts[-1])


@dataclass(frozen=True)
class GraphParams:
    """The node's place in the ROS 2 graph, declared once: the ros2 service, `gridslam run --ros2`
    and the `ros2:` source take these settings (keys of `[ros2]`, flags of the same names)."""

    LABEL = "ros2"

    ros_domain_id: int = setting(0, help="ROS 2 domain of the graph (the environment's ROS_DOMAIN_ID when set)",
                                 ge=0, le=232)
    ros_namespace: str = setting("/gridslam", help="ROS namespace of the node and of its relative topics")
    ros_distro: str = setting(DEFAULT_DISTRO, help="ROS 2 distribution of the graph (message definitions, type hashes)",
                              choices=DISTROS)
    ros2_keys: str = setting("rmw_zenoh", help="key expressions: rmw_zenoh's, or zenoh-bridge-ros2dds' (plain topic "
                                               "names, no attachment) for a DDS graph behind the bridge",
                             choices=KEY_STYLES)
