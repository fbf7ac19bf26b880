"""Transport over TLS with the shipped deploy/tls configs and certificates made by
deploy/make-certs.sh (into the test's folder): a client that trusts the CA exchanges messages
through a TLS router; under mutual TLS a client with a certificate from the CA exchanges
messages, while one without a certificate, one with a certificate from another CA, and a
plain TCP client cannot connect; a client refuses a router that its CA did not sign."""

import threading

import pytest
import zenoh

from services.common import codec, topics
from services.common.errors import ConfigError
from services.common.runtime import RuntimeConfig, open_session
from tests.messages import sample_messages
from tests.netutil import endpoint, free_port, wait_for
from tests.tlsutil import (
    CLIENT_MTLS, CLIENT_TLS, ROUTER_MTLS, ROUTER_TLS, client_runtime, make_certs, router_runtime, tls_endpoint, tls_paths,
)


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    return make_certs(tmp_path_factory.mktemp("certs"))


@pytest.fixture(scope="module")
def rogue_certs(tmp_path_factory):
    """A second, unrelated CA with its own certificates for the same roles."""
    return make_certs(tmp_path_factory.mktemp("rogue"))


def exchange(publisher: zenoh.Session, subscriber: zenoh.Session):
    """Publish an EgoMotion on the publisher until the subscriber has decoded it; returns (sent, received)."""
    message = next(m for m in sample_messages() if m.KIND == "EgoMotion")
    key = topics.key("robot0", "egomotion")
    received = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            received.append(codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding)))

    subscription = subscriber.declare_subscriber(key, on_sample)
    try:
        def arrived():
            publisher.put(key, codec.encode(message), encoding=zenoh.Encoding(codec.encoding_of(message)))
            with lock:
                return list(received)
        return message, wait_for(arrived, timeout=10, period=0.1)
    finally:
        subscription.undeclare()


@pytest.mark.parametrize("router_config, client_config", [(ROUTER_TLS, CLIENT_TLS), (ROUTER_MTLS, CLIENT_MTLS)],
                         ids=["tls", "mutual-tls"])
def test_client_with_valid_certificate_exchanges_messages(certs, router_config, client_config):
    port = free_port()
    router = open_session(router_runtime(port, router_config, certs))
    sessions = []
    try:
        # Both names the router certificate carries: a DNS name and an IP address.
        sessions.append(open_session(client_runtime(port, client_config, certs, "egomotion", host="localhost")))
        sessions.append(open_session(client_runtime(port, client_config, certs, "observer", host="127.0.0.1")))
        sent, received = exchange(*sessions)
        assert received[0] == sent
    finally:
        for session in (*sessions, router):
            session.close()


def test_mutual_tls_refuses_clients_without_a_valid_certificate(certs, rogue_certs):
    port = free_port()
    router = open_session(router_runtime(port, ROUTER_MTLS, certs))
    # A certificate and key from another CA, while trusting the right CA for the router.
    foreign = {**tls_paths(rogue_certs, "egomotion"), "transport/link/tls/root_ca_certificate": f'"{certs / "ca.pem"}"'}
    refused = {
        "no client certificate": client_runtime(port, CLIENT_TLS, certs, "egomotion"),
        "certificate of another CA": RuntimeConfig(connect=[tls_endpoint(port)], zenoh_config=CLIENT_MTLS, cfg=foreign),
        "plain TCP": RuntimeConfig(connect=[endpoint(port)]),
    }
    try:
        valid = open_session(client_runtime(port, CLIENT_MTLS, certs, "egomotion"))   # the router does accept clients
        valid.close()
        for reason, runtime in refused.items():
            with pytest.raises(ConfigError, match="cannot open a Zenoh session"):
                session = open_session(runtime)
                session.close()
                pytest.fail(f"a client with {reason} connected")
    finally:
        router.close()


def test_client_refuses_a_router_signed_by_another_ca(certs, rogue_certs):
    port = free_port()
    router = open_session(router_runtime(port, ROUTER_TLS, rogue_certs))
    try:
        with pytest.raises(ConfigError, match="cannot open a Zenoh session"):
            open_session(client_runtime(port, CLIENT_TLS, certs, "observer")).close()
    finally:
        router.close()
