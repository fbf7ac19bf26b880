"""The Foxglove server's front door (services/ros/ws_relay.py) and its clients' history
(services/ros/foxglove.py), in-process with the real foxglove-sdk server behind the relay and
the `websockets` client in front: either subprotocol is accepted and named back, anything else
is one HTTP 400 and one log line, and a client that subscribes late is sent the run so far,
then every new message, none twice, without repeating it to the other clients."""

from __future__ import annotations

import contextlib
import json
import logging
import struct
import time
import urllib.error
import urllib.request

import pytest

from tests.extras import require

require("foxglove", "foxglove")
require("websockets", "test")

import foxglove  # noqa: E402
from websockets.exceptions import InvalidStatus  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from services.common.recovery import REPLAY_FRAMES  # noqa: E402
from services.common.runtime import RuntimeConfig  # noqa: E402
from services.ros.foxglove import FoxgloveConfig, FoxgloveService, RunHistory  # noqa: E402
from services.ros2wire.messages import MARKERS_TOPIC  # noqa: E402
from services.ros.ws_relay import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL, Head, SubprotocolRelay, choose_subprotocol  # noqa: E402


def test_head_parsing_and_the_subprotocol_chosen():
    head = Head.parse(b"GET / HTTP/1.1\r\nHost: x\r\nSec-WebSocket-Protocol: a, foxglove.websocket.v1\r\n"
                      b"sec-websocket-protocol: foxglove.sdk.v1\r\nUpgrade: websocket")
    assert head.values("Sec-WebSocket-Protocol") == ["a", LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL]
    replaced = head.replace("Sec-WebSocket-Protocol", SDK_SUBPROTOCOL)
    assert replaced.fields == (("Host", "x"), ("Sec-WebSocket-Protocol", SDK_SUBPROTOCOL), ("Upgrade", "websocket"))
    assert replaced.encode().endswith(b"\r\nUpgrade: websocket\r\n\r\n")
    assert choose_subprotocol([LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL]) == SDK_SUBPROTOCOL   # the SDK's name first
    assert choose_subprotocol([LEGACY_SUBPROTOCOL]) == LEGACY_SUBPROTOCOL
    assert choose_subprotocol(["foxglove.websocket.v2", ""]) is None
    with pytest.raises(ValueError, match="malformed"):
        Head.parse(b"GET / HTTP/1.1\r\nno colon here")


class SdkBackend:
    """A bare foxglove-sdk server on a loopback port, as the Foxglove service makes one per client."""

    def __init__(self):
        self.server = foxglove.start_server(host="127.0.0.1", port=0, context=foxglove.Context())
        self.port = self.server.port
        self.closed = False

    def close(self) -> None:
        self.closed = True
        self.server.stop()


def test_the_sdks_own_server_refuses_the_old_subprotocol():
    """Why the relay exists: foxglove-sdk answers a client offering only foxglove.websocket.v1 with 400."""
    backend = SdkBackend()
    try:
        with pytest.raises(InvalidStatus, match="400"):
            connect(f"ws://127.0.0.1:{backend.port}", subprotocols=[LEGACY_SUBPROTOCOL], open_timeout=5)
        with connect(f"ws://127.0.0.1:{backend.port}", subprotocols=[SDK_SUBPROTOCOL], open_timeout=5) as ws:
            assert ws.subprotocol == SDK_SUBPROTOCOL
    finally:
        backend.close()


def test_the_relay_accepts_either_subprotocol_and_refuses_others_in_one_line(caplog):
    backends = []

    def open_backend():
        backends.append(SdkBackend())
        return backends[-1]

    relay = SubprotocolRelay("127.0.0.1", 0, open_backend)
    relay.start()
    url = f"ws://127.0.0.1:{relay.port}"
    try:
        for offered, chosen in (([LEGACY_SUBPROTOCOL], LEGACY_SUBPROTOCOL), ([SDK_SUBPROTOCOL], SDK_SUBPROTOCOL),
                                ([LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL], SDK_SUBPROTOCOL)):
            with connect(url, subprotocols=offered, open_timeout=5) as ws:
                assert ws.subprotocol == chosen   # the name the client offered, answered back
                assert json.loads(ws.recv(timeout=5))["op"] == "serverInfo"   # the SDK's server speaks through it
        assert relay.connections == 3 and len(backends) == 3
        for backend in backends:   # each client's own server, closed when its client left
            deadline = time.monotonic() + 5
            while not backend.closed and time.monotonic() < deadline:
                time.sleep(0.02)
            assert backend.closed
        with caplog.at_level(logging.WARNING, logger="services.ros.ws_relay"):
            with pytest.raises(InvalidStatus) as refused:
                connect(url, subprotocols=["foxglove.websocket.v2"], open_timeout=5)
        assert refused.value.response.status_code == 400
        assert refused.value.response.body == b"Offer the WebSocket subprotocol foxglove.sdk.v1 or foxglove.websocket.v1.\n"
        lines = [record.getMessage() for record in caplog.records]
        assert len(lines) == 1 and "offering foxglove.websocket.v2" in lines[0] and "foxglove.websocket.v1" in lines[0]
        assert relay.refused == 1 and len(backends) == 3   # no server was made for it
        with pytest.raises(urllib.error.HTTPError) as plain:   # a browser visiting the address
            urllib.request.urlopen(f"http://127.0.0.1:{relay.port}/", timeout=5)
        assert plain.value.code == 426 and b"Foxglove WebSocket" in plain.value.read()
    finally:
        relay.stop()
    with pytest.raises(OSError):
        connect(url, subprotocols=[SDK_SUBPROTOCOL], open_timeout=2)


def test_history_keeps_every_pose_up_to_its_limit_and_the_newest_map():
    history = RunHistory(limit=3)
    for stamp in range(5):
        history.add("/gridslam/map", stamp, b"pose%d" % stamp)
        history.add(MARKERS_TOPIC, stamp, b"map%d" % stamp)
    assert history.messages("/gridslam/map") == [(2, b"pose2"), (3, b"pose3"), (4, b"pose4")]
    assert history.messages(MARKERS_TOPIC) == [(4, b"map4")]
    assert history.capacity(["/gridslam/map", MARKERS_TOPIC]) == 4
    history.add("/fleet/b/pose", 4, b"b4")
    history.clear(["/gridslam/map", MARKERS_TOPIC])   # a new run: the pipeline's topics, not the fleet's
    assert history.messages("/gridslam/map") == [] and history.messages("/fleet/b/pose") == [(4, b"b4")]


class Client:
    """A Foxglove client of the service (through its relay), subscribed to one topic."""

    def __init__(self, port: int, topic: str):
        self.stack = contextlib.ExitStack()
        self.ws = self.stack.enter_context(connect(f"ws://127.0.0.1:{port}", subprotocols=[LEGACY_SUBPROTOCOL],
                                                   max_size=None, open_timeout=5))
        while True:
            message = json.loads(self.ws.recv(timeout=5))
            if message["op"] == "advertise":
                break
        channel = next(c for c in message["channels"] if c["topic"] == topic)
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel["id"]}]}))

    def stamps(self, quiet: float = 0.5) -> list[int]:
        stamps = []
        while True:
            try:
                frame = self.ws.recv(timeout=quiet)
            except TimeoutError:
                return stamps
            if isinstance(frame, bytes) and frame[0] == 0x01:
                stamps.append(struct.unpack_from("<IQ", frame, 1)[1])

    def close(self) -> None:
        self.stack.close()


def test_a_client_subscribing_late_gets_the_run_so_far_then_every_new_message_once():
    service = FoxgloveService(RuntimeConfig(), FoxgloveConfig(port=0, history=100), "test")
    service.relay.start()

    def publish(stamp: int) -> None:
        service._log(stamp, *service.ros.planar_pose("map", stamp, 0.1 * stamp, 0.0, 0.0))

    try:
        for stamp in range(1, 6):
            publish(stamp)
        first = Client(service.relay.port, "/gridslam/map")
        assert first.stamps() == [1, 2, 3, 4, 5]   # the run so far, on subscribing
        publish(6)
        second = Client(service.relay.port, "/gridslam/map")
        assert second.stamps() == [1, 2, 3, 4, 5, 6]
        publish(7)
        assert first.stamps() == [6, 7] and second.stamps() == [7]   # the second's history went to it alone
        assert len(service.clients) == 2 and service.extra_counters()["clients"] == 2
        first.close()
        second.close()
        deadline = time.monotonic() + 5
        while service.clients and time.monotonic() < deadline:
            time.sleep(0.02)
        assert service.clients == []
        # A pose sent again (a stage's outputs replayed, seq back by a few, even from before the
        # first this bridge heard: it came up late) is not kept twice; a new run on the robot (its
        # seq back by more than a frame sent again can be) starts the history afresh.
        assert [service._fresh("map/pose", seq) for seq in range(20, 40)] == [True] * 20
        assert [service._fresh("map/pose", seq) for seq in (10, 25, 39)] == [False] * 3
        assert all(service._fresh("map/pose", seq) for seq in range(40, 40 + REPLAY_FRAMES))
        assert service.history.messages("/gridslam/map")[0][0] == 1
        assert service._fresh("map/pose", 0) and service.history.messages("/gridslam/map") == []
        publish(100)
        third = Client(service.relay.port, "/gridslam/map")
        assert third.stamps() == [100]
        third.close()
    finally:
        service.close_server()
