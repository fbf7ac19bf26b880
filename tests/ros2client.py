"""An outside rmw_zenoh client for the tests: zenoh-ros2-sdk (PyPI), whose authors test it
against real Jazzy rmw_zenoh, with the message definitions of the `ros-kilted-*` wheels
(share/<pkg>/msg/*.msg) and tf2_msgs' one-line TFMessage (no wheel of it on PyPI). It opens
its own Zenoh session (rmw_zenoh's default session config) to the router on 127.0.0.1:PORT."""

from __future__ import annotations

import importlib
import shutil
import sys
import threading
from pathlib import Path


from tests.extras import require

SHARE = Path(sys.prefix) / "share"
PACKAGES = ("builtin_interfaces", "std_msgs", "geometry_msgs", "nav_msgs", "sensor_msgs", "visualization_msgs")


def sdk():
    """The zenoh_ros2_sdk module: skipped where the test extra is missing, a failure in CI."""
    return require("zenoh_ros2_sdk", "test")


def message_folder(folder: Path) -> Path:
    """A folder of ROS 2 .msg files laid out as the SDK reads them (<pkg>/msg/<Type>.msg)."""
    for package in PACKAGES:
        shutil.copytree(SHARE / package / "msg", folder / package / "msg", dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("*.idl", "*.json"))
    (folder / "tf2_msgs" / "msg").mkdir(parents=True, exist_ok=True)
    (folder / "tf2_msgs" / "msg" / "TFMessage.msg").write_text("geometry_msgs/TransformStamped[] transforms\n")
    return folder


class Client:
    """The SDK's shared session on the router at `port`, its subscriptions and publishers."""

    def __init__(self, port: int, folder: Path):
        self.sdk = sdk()
        self.port = port
        self.sdk.get_registry(str(message_folder(folder)))
        self.received: dict[str, list] = {}
        self.lock = threading.Lock()
        self.endpoints = []

    def subscribe(self, topic: str, msgtype: str) -> None:
        self.received[topic] = []

        def keep(message, topic=topic):
            with self.lock:
                self.received[topic].append(message)

        self.endpoints.append(self.sdk.ROS2Subscriber(topic, msgtype, keep, router_port=self.port,
                                                      node_name="test_listener"))

    def publisher(self, topic: str, msgtype: str, **options):
        publisher = self.sdk.ROS2Publisher(topic, msgtype, router_port=self.port, node_name="test_camera", **options)
        self.endpoints.append(publisher)
        return publisher

    def topics(self) -> dict[str, list[str]]:
        return dict(self.sdk.get_topic_names_and_types(router_port=self.port, timeout=1.0))

    def nodes(self) -> set[tuple[str, str]]:
        """(namespace, name) of every node token in domain 0."""
        session = self.sdk.ZenohSession.get_instance(router_port=self.port)
        found = set()
        for reply in session.liveliness.get("@ros2_lv/0/*/*/*/NN/**", timeout=1.0):
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")
                found.add((parts[7].replace("%", "/"), parts[8]))
        return found

    def close(self) -> None:
        for endpoint in self.endpoints:
            try:
                endpoint.close()
            except Exception:
                pass
        session = self.sdk.ZenohSession._instance
        if session is not None:
            session.close()
        # The SDK's message registry is global and remembers the types it loaded into the closed
        # session's type store; the next test's session has an empty store, so it starts afresh.
        importlib.import_module("zenoh_ros2_sdk.message_registry")._registry = None
