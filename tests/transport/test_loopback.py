"""Transport: a router and two client sessions in one process exchange every message type on
loopback with multicast off; payloads decode through the codec on the receiving side."""

import threading

import zenoh

from services.common import codec, topics
from tests.messages import sample_messages
from tests.netutil import client_session, free_port, router_session, wait_for


def test_every_message_crosses_a_router():
    port = free_port()
    router = router_session(port)
    publisher_session, subscriber_session = client_session(port), client_session(port)
    received: dict[str, object] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        message = codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding))
        with lock:
            received[str(sample.key_expr)] = message

    try:
        subscriber = subscriber_session.declare_subscriber(f"{topics.PREFIX}/robot0/**", on_sample)
        messages = {topics.key("robot0", f"test/{m.KIND}"): m for m in sample_messages()}

        def all_received():
            for key, message in messages.items():
                publisher_session.put(key, codec.encode(message), encoding=zenoh.Encoding(codec.encoding_of(message)))
            with lock:
                return set(received) == set(messages)

        wait_for(all_received, timeout=10, period=0.2)
        assert received == messages
        subscriber.undeclare()
    finally:
        for session in (publisher_session, subscriber_session, router):
            session.close()


def test_liveliness_token_is_seen_and_goes_away():
    port = free_port()
    router = router_session(port)
    a, b = client_session(port), client_session(port)
    key = topics.health_key("robot0", "gridcells", "test-1")
    try:
        token = a.liveliness().declare_token(key)

        def live_keys():
            return [str(r.ok.key_expr) for r in b.liveliness().get(f"{topics.PREFIX}/*/health/**", timeout=1) if r.ok]

        assert wait_for(lambda: key in live_keys())
        token.undeclare()
        wait_for(lambda: key not in live_keys())
    finally:
        for session in (a, b, router):
            session.close()
