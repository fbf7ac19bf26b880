"""rmw_zenoh's wire format (services/ros2wire/rmw_zenoh.py) against rmw_zenoh's own examples and
ROS 2's own code: the keys and tokens of rmw_zenoh's docs/design.md (kilted 0.6.x and rolling;
jazzy 0.2.x has the same), the RIHS01 hashes of rosidl's type-description files (the
`ros-kilted-*` wheels) and of rosbags, the attachment as Zenoh's deserializer reads it, and
every message the live node publishes parsed by real rclpy into the fields that were sent."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from services.ros2wire import rmw_zenoh
from services.ros2wire.rmw_zenoh import Qos, WireError
from tests.extras import require

require("rosbags", "ros")

SHARE = Path(sys.prefix) / "share"
CHATTER_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
# The types the live node publishes or reads.
TYPES = ("nav_msgs/msg/Odometry", "tf2_msgs/msg/TFMessage", "geometry_msgs/msg/PoseWithCovarianceStamped",
         "nav_msgs/msg/Path", "visualization_msgs/msg/MarkerArray", "sensor_msgs/msg/Image",
         "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo")


# --------------------------------------------------------------------------- design.md's examples
def test_data_keys_equal_the_design_documents_examples():
    assert rmw_zenoh.topic_key(0, "/chatter", "std_msgs/msg/String", CHATTER_HASH) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{CHATTER_HASH}"
    assert rmw_zenoh.topic_key(0, rmw_zenoh.fully_qualified("/robot1", "chatter"), "std_msgs/msg/String", CHATTER_HASH) == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{CHATTER_HASH}"
    assert rmw_zenoh.topic_key(2, "/add_two_ints", "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH) == \
        f"2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}"


def test_tokens_equal_the_design_documents_examples():
    listener = "aac3178e146ba6f1fc6e6a4085e77f21"
    talker = "8b20917502ee955ac4476e0266340d5c"
    assert rmw_zenoh.node_token(0, listener, 0, "/", "listener") == f"@ros2_lv/0/{listener}/0/0/NN/%/%/listener"
    assert rmw_zenoh.endpoint_token("MS", 0, listener, 0, 10, "/", "listener", "/chatter", "std_msgs/msg/String",
                                    CHATTER_HASH, Qos(depth=10)) == \
        f"@ros2_lv/0/{listener}/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/{CHATTER_HASH}/::,10:,:,:,,"
    assert rmw_zenoh.endpoint_token("MP", 0, talker, 0, 10, "/", "talker", "/chatter", "std_msgs/msg/String",
                                    CHATTER_HASH, Qos(depth=7)) == \
        f"@ros2_lv/0/{talker}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{CHATTER_HASH}/::,7:,:,:,,"


def test_tokens_in_a_namespace_mangle_every_slash():
    zid = "aac3178e146ba6f1fc6e6a4085e77f21"
    namespace = rmw_zenoh.normalise_namespace("gridslam/")
    topic = rmw_zenoh.fully_qualified(namespace, "odom")
    assert (namespace, topic) == ("/gridslam", "/gridslam/odom")
    assert rmw_zenoh.node_token(3, zid, 0, namespace, "gridslam") == f"@ros2_lv/3/{zid}/0/0/NN/%/%gridslam/gridslam"
    token = rmw_zenoh.endpoint_token("MP", 3, zid, 0, 1, namespace, "gridslam", topic, "nav_msgs/msg/Odometry", "H",
                                     rmw_zenoh.RELIABLE_QOS)
    assert token == f"@ros2_lv/3/{zid}/0/1/MP/%/%gridslam/gridslam/%gridslam%odom/nav_msgs::msg::dds_::Odometry_/H/::,10:,:,:,,"
    assert rmw_zenoh.topic_key(3, topic, "nav_msgs/msg/Odometry", "H") == "3/gridslam/odom/nav_msgs::msg::dds_::Odometry_/H"
    assert rmw_zenoh.fully_qualified(namespace, "/tf") == "/tf"
    with pytest.raises(WireError, match="namespace"):
        rmw_zenoh.normalise_namespace("/robot 1")


def test_qos_fields_are_empty_where_they_are_rmw_zenohs_default():
    assert Qos().encode() == "::,:,:,:,,"
    assert rmw_zenoh.SENSOR_QOS.encode() == "2::,5:,:,:,,"
    assert rmw_zenoh.LATCHED_QOS.encode() == ":1:,1:,:,:,,"
    assert Qos(history=rmw_zenoh.KEEP_ALL, deadline=(1, 500)).encode() == "::2,:1,500:,:,,"


def test_humble_has_no_type_hash():
    assert rmw_zenoh.type_hash("humble", CHATTER_HASH) == "TypeHashNotSupported"
    assert all(rmw_zenoh.type_hash(d, CHATTER_HASH) == CHATTER_HASH for d in ("jazzy", "kilted", "rolling"))


def test_keys_read_back():
    key = rmw_zenoh.topic_key(0, "/cam/image_raw", "sensor_msgs/msg/Image", "H")
    assert rmw_zenoh.parse_topic_key(key, "rmw_zenoh") == rmw_zenoh.TopicKey("/cam/image_raw", "sensor_msgs/msg/Image", "H")
    assert rmw_zenoh.parse_topic_key("cam/image_raw", "bridge").topic == "/cam/image_raw"
    with pytest.raises(WireError):
        rmw_zenoh.parse_topic_key("0/cam/image_raw/not_a_type/H", "rmw_zenoh")


# --------------------------------------------------------------------------- attachment and GID
def test_attachment_is_what_zenohs_serializer_writes_and_reads():
    import zenoh
    import zenoh.ext as zext
    gid = bytes(range(16))
    data = rmw_zenoh.attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(data) == 33
    assert data == zext.z_serialize((zext.Int64(7), zext.Int64(1_700_000_000_123_456_789), gid)).to_bytes()
    sequence, stamp, back = zext.z_deserialize(tuple[zext.Int64, zext.Int64, bytes], zenoh.ZBytes(data))
    assert (int(sequence), int(stamp), back) == (7, 1_700_000_000_123_456_789, gid)
    assert rmw_zenoh.parse_attachment(data) == (7, 1_700_000_000_123_456_789, gid)
    for bad in (None, b"", data[:-1], data[:16] + b"\x18" + data[17:]):
        with pytest.raises(WireError):
            rmw_zenoh.parse_attachment(bad)


def test_gid_is_xxh3_128_of_the_token_low_half_first():
    xxhash = require("xxhash", "ros")
    token = "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    value = xxhash.xxh3_128_intdigest(token.encode())
    assert rmw_zenoh.gid(token) == (value & (2**64 - 1)).to_bytes(8, "little") + (value >> 64).to_bytes(8, "little")
    assert rmw_zenoh.gid(token) != rmw_zenoh.gid(token + "x")


# --------------------------------------------------------------------------- type hashes
def rosidl_hash(msgtype: str, tmp_path: Path) -> str:
    """The RIHS01 hash rosidl gives `msgtype`: the JSON a `ros-kilted-*` wheel ships, or, for
    tf2_msgs (no wheel on PyPI), rosidl's generator run here on its definition."""
    shipped = SHARE / f"{msgtype}.json"
    if shipped.is_file():
        return json.loads(shipped.read_text())["type_hashes"][0]["hash_string"]
    assert msgtype == "tf2_msgs/msg/TFMessage", f"{shipped} is missing"
    from rosidl_adapter.msg import convert_msg_to_idl
    from rosidl_generator_type_description import generate_type_hash

    package = tmp_path / "tf2_msgs"
    (package / "msg").mkdir(parents=True)
    (package / "msg" / "TFMessage.msg").write_text("geometry_msgs/TransformStamped[] transforms\n")   # tf2_msgs' definition
    convert_msg_to_idl(package, "tf2_msgs", Path("msg/TFMessage.msg"), package / "msg")
    arguments = tmp_path / "args.json"
    arguments.write_text(json.dumps({"package_name": "tf2_msgs", "output_dir": str(tmp_path / "out"),
                                     "idl_tuples": [f"{package}:msg/TFMessage.idl"],
                                     "include_paths": [f"geometry_msgs:{SHARE / 'geometry_msgs'}",
                                                       f"std_msgs:{SHARE / 'std_msgs'}",
                                                       f"builtin_interfaces:{SHARE / 'builtin_interfaces'}"]}))
    (generated,) = generate_type_hash(str(arguments))
    return json.loads(Path(generated).read_text())["type_hashes"][0]["hash_string"]


@pytest.mark.parametrize("distro", ["jazzy", "kilted", "rolling"])
def test_type_hashes_equal_rosidls_and_rosbags(distro, tmp_path):
    require("rosidl_generator_type_description", "test")
    from rosbags.typesys import Stores, get_typestore

    from services.ros2wire.messages import RosMessages

    ros = RosMessages(distro)
    kilted = get_typestore(Stores.ROS2_KILTED)
    for msgtype in TYPES:
        expected = rosidl_hash(msgtype, tmp_path / msgtype.replace("/", "_"))
        assert ros.rihs01(msgtype) == expected == kilted.hash_rihs01(msgtype), msgtype


# --------------------------------------------------------------------------- CDR read by rclpy
@pytest.fixture(scope="module")
def rclpy_serialization():
    require("rclpy", "test")
    from rclpy.serialization import deserialize_message

    return deserialize_message


def xyz(v):
    return (v.x, v.y, v.z)


def test_every_published_message_parses_in_rclpy_into_what_was_sent(rclpy_serialization):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry, Path as RosPath
    from sensor_msgs.msg import Image
    from visualization_msgs.msg import MarkerArray

    from services.ros import projection
    from services.ros2wire.messages import MapState, RosMessages

    deserialize = rclpy_serialization
    ros = RosMessages("kilted")
    stamp = 1_700_000_123_456_789_012
    covariance = np.arange(36, dtype=float) / 100
    odometry = deserialize(ros.odometry(stamp, "odom", "base_link", (1.5, -2.25, 0.0), (0.0, 0.0, 0.6, 0.8), covariance,
                                        (0.5, 0.0, 0.0), (0.0, 0.0, 0.1)), Odometry)
    assert (odometry.header.stamp.sec, odometry.header.stamp.nanosec) == divmod(stamp, 1_000_000_000)
    assert (odometry.header.frame_id, odometry.child_frame_id) == ("odom", "base_link")
    assert xyz(odometry.pose.pose.position) == (1.5, -2.25, 0.0)
    assert (*xyz(odometry.pose.pose.orientation), odometry.pose.pose.orientation.w) == (0.0, 0.0, 0.6, 0.8)
    assert np.array_equal(np.asarray(odometry.pose.covariance), covariance)
    assert xyz(odometry.twist.twist.linear) == (0.5, 0.0, 0.0) and odometry.twist.twist.angular.z == 0.1

    pose = deserialize(ros.pose_with_covariance(stamp, "map", (3.0, 4.0, 0.0), (0.0, 0.0, 0.0, 1.0), covariance),
                       PoseWithCovarianceStamped)
    assert pose.header.frame_id == "map" and xyz(pose.pose.pose.position) == (3.0, 4.0, 0.0)
    assert np.array_equal(np.asarray(pose.pose.covariance), covariance)

    path = deserialize(ros.path(stamp, "map", [(stamp - 10, 0.0, 0.0, 0.0), (stamp, 1.0, 2.0, np.pi / 2)]), RosPath)
    assert path.header.frame_id == "map" and len(path.poses) == 2
    assert xyz(path.poses[1].pose.position) == (1.0, 2.0, 0.0)
    assert path.poses[1].pose.orientation.z == pytest.approx(np.sqrt(0.5))
    assert path.poses[0].header.stamp.nanosec == (stamp - 10) % 1_000_000_000

    state = MapState()
    state.apply([(0, 0.0, 0.0), (1, 2.0, 0.0), (2, 2.0, 3.0)], [(0, 1, 0), (1, 2, 0), (2, 0, 1)])
    markers = deserialize(ros.marker_array(stamp, state), MarkerArray)
    by_namespace = {m.ns: m for m in markers.markers}
    assert set(by_namespace) == {"experiences", "links", "closures"}
    assert [(p.x, p.y) for p in by_namespace["experiences"].points] == [(0.0, 0.0), (2.0, 0.0), (2.0, 3.0)]
    assert [(p.x, p.y) for p in by_namespace["closures"].points] == [(2.0, 3.0), (0.0, 0.0)]
    assert by_namespace["experiences"].header.frame_id == "map"

    pixels = (np.arange(12 * 7) % 256).astype(np.uint8).reshape(7, 12)
    image = deserialize(ros.mono_image(stamp, "grid", pixels), Image)
    assert (image.height, image.width, image.encoding, image.step) == (7, 12, "mono8", 12)
    assert np.array_equal(np.asarray(image.data, dtype=np.uint8).reshape(7, 12), pixels)

    # The projection's messages, as the node sends them, parse too.
    live = projection.Projection(ros)
    sent = live.grid_pose(0, stamp, (0.0, 0.0, 0.0), increment_covariance=[0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.001])
    sent += live.grid_pose(1, stamp + 10**8, (1.0, 0.0, 0.0), increment_covariance=[0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.001])
    odom = deserialize(dict(sent)[projection.ODOM], Odometry)
    assert odom.pose.pose.position.x == 1.0 and odom.pose.covariance[0] == pytest.approx(0.01)
    assert odom.pose.covariance[7] == pytest.approx(0.01 + 0.001)   # the turn's share: (1 m · σ_yaw)²
    assert odom.pose.covariance[35] == pytest.approx(0.001)


def test_tf_messages_hold_the_transforms_sent():
    # tf2_msgs has no wheel on PyPI, so rclpy cannot load its type: rosbags' reader (a CDR
    # decoder of its own) reads it here, and zenoh-ros2-sdk's in the end-to-end test.
    from services.ros2wire.messages import RosMessages

    ros = RosMessages("jazzy")
    data = ros.transforms(42, [("map", "odom", (1.0, 2.0, 0.0), (0.0, 0.0, 0.6, 0.8)),
                               ("odom", "base_link", (3.0, 4.0, 0.0), (0.0, 0.0, 0.0, 1.0))])
    message = ros.store.deserialize_cdr(data, "tf2_msgs/msg/TFMessage")
    assert [(t.header.frame_id, t.child_frame_id, t.transform.translation.x, t.transform.rotation.z)
            for t in message.transforms] == [("map", "odom", 1.0, 0.6), ("odom", "base_link", 3.0, 0.0)]
    assert data[:4] == b"\x00\x01\x00\x00"   # CDR, little endian
