"""The Foxglove server's front door: a TCP relay that accepts the WebSocket handshake of either
Foxglove subprotocol and passes the connection on to a foxglove-sdk server.

The Foxglove WebSocket protocol was named `foxglove.websocket.v1` (its specification,
foxglove/ws-protocol docs/spec.md: "The current version of this document corresponds to
subprotocol foxglove.websocket.v1"); foxglove-sdk's server accepts only the later name
`foxglove.sdk.v1` and answers any other offer with HTTP 400 (foxglove-sdk,
rust/foxglove/src/websocket/handshake.rs). Clients still offering only the first name (the npm
`@foxglove/ws-protocol` client, Lichtblick before its December 2025 release, older Foxglove
Studio) would be refused. Foxglove says the two are the same protocol under two names, so the
relay reads the client's upgrade request, offers the SDK `foxglove.sdk.v1`, writes back in the
SDK's answer the name the client chose, and from then on copies bytes both ways untouched
(the WebSocket accept key depends on the client's key only, RFC 6455 §4.2.2, so the handshake
stays valid).

Every connection gets its own backend (`open_backend`): the Foxglove service gives each client
a server of its own, so that it can send one client the run so far without repeating it to
the others (foxglove.py).
"""

from __future__ import annotations

import logging
import socket
import threading
from dataclasses import dataclass
from typing import Callable, Protocol

log = logging.getLogger(__name__)

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
ACCEPTED = (SDK_SUBPROTOCOL, LEGACY_SUBPROTOCOL)   # in order of preference
HEAD_LIMIT = 16384            # bytes of an HTTP head before the request is refused
HANDSHAKE_TIMEOUT_S = 10.0
CHUNK = 65536


class Backend(Protocol):
    port: int

    def close(self) -> None: ...


@dataclass(frozen=True)
class Head:
    """An HTTP/1.1 request or response head: its first line and its header fields, in order."""

    start_line: str
    fields: tuple[tuple[str, str], ...]

    @classmethod
    def parse(cls, data: bytes) -> Head:
        lines = data.decode("latin-1").split("\r\n")
        fields = []
        for line in lines[1:]:
            if not line:
                continue
            name, sep, value = line.partition(":")
            if not sep:
                raise ValueError(f"malformed header line {line[:60]!r}")
            fields.append((name.strip(), value.strip()))
        return cls(lines[0], tuple(fields))

    def values(self, name: str) -> list[str]:
        """Every comma-separated value of the header fields named `name` (any case)."""
        return [part.strip() for key, value in self.fields if key.lower() == name.lower()
                for part in value.split(",") if part.strip()]

    def replace(self, name: str, value: str) -> Head:
        """The head with every field `name` replaced by one `name: value` where the first was."""
        fields, placed = [], False
        for key, old in self.fields:
            if key.lower() != name.lower():
                fields.append((key, old))
            elif not placed:
                fields.append((key, value))
                placed = True
        if not placed:
            fields.append((name, value))
        return Head(self.start_line, tuple(fields))

    def encode(self) -> bytes:
        return ("\r\n".join([self.start_line, *(f"{key}: {value}" for key, value in self.fields)]) + "\r\n\r\n").encode("latin-1")


def choose_subprotocol(offered: list[str]) -> str | None:
    """The subprotocol the relay agrees to, of those the client offered (None: none of ours)."""
    return next((name for name in ACCEPTED if name in offered), None)


def is_websocket_upgrade(head: Head) -> bool:
    return "websocket" in [value.lower() for value in head.values("Upgrade")]


def http_response(status: str, body: str) -> bytes:
    data = body.encode()
    return (f"HTTP/1.1 {status}\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Length: {len(data)}\r\n"
            f"Connection: close\r\n\r\n").encode() + data


def read_head(sock: socket.socket) -> tuple[bytes, bytes]:
    """(the head up to and without its blank line, the bytes read after it). ValueError when the
    peer closes first or the head is larger than HEAD_LIMIT."""
    data = b""
    while b"\r\n\r\n" not in data:
        if len(data) > HEAD_LIMIT:
            raise ValueError(f"HTTP head larger than {HEAD_LIMIT} bytes")
        chunk = sock.recv(4096)
        if not chunk:
            raise ValueError("connection closed during the handshake")
        data += chunk
    head, _, rest = data.partition(b"\r\n\r\n")
    return head, rest


class SubprotocolRelay:
    """Listens on (host, port); each WebSocket client offering a Foxglove subprotocol is joined
    to a backend of its own (`open_backend()`, a server on 127.0.0.1:backend.port)."""

    def __init__(self, host: str, port: int, open_backend: Callable[[], Backend], name: str = "foxglove"):
        self.open_backend, self.name = open_backend, name
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.listener = socket.socket(family, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.listener.bind((host, port))
            self.listener.listen(16)
        except OSError:
            self.listener.close()
            raise
        self.port = self.listener.getsockname()[1]
        self.refused = 0                   # upgrade requests offering no Foxglove subprotocol
        self.connections = 0               # clients joined to a backend so far
        self._open: set[socket.socket] = set()
        self._lock = threading.Lock()
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._accept, name=f"{self.name}-relay", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopped.set()
        try:
            self.listener.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.listener.close()
        with self._lock:
            sockets, self._open = list(self._open), set()
        for sock in sockets:
            _close(sock)
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def _accept(self) -> None:
        while not self._stopped.is_set():
            try:
                client, address = self.listener.accept()
            except OSError:
                return   # stopped
            threading.Thread(target=self._serve, args=(client, address), name=f"{self.name}-client", daemon=True).start()

    def _track(self, *sockets: socket.socket) -> bool:
        with self._lock:
            if self._stopped.is_set():
                return False
            self._open.update(sockets)
            return True

    def _serve(self, client: socket.socket, address) -> None:
        peer = f"{address[0]}:{address[1]}"
        backend, upstream = None, None
        try:
            if not self._track(client):
                return
            client.settimeout(HANDSHAKE_TIMEOUT_S)
            try:
                data, rest = read_head(client)
                head = Head.parse(data)
            except (ValueError, OSError) as error:
                log.warning("%s: dropped a connection from %s: %s", self.name, peer, error)
                return
            if not is_websocket_upgrade(head):
                client.sendall(http_response("426 Upgrade Required", "This is gridslam's Foxglove WebSocket server: in "
                                             "Foxglove, open a Foxglove WebSocket connection to this address (ws://).\n"))
                return
            offered = head.values("Sec-WebSocket-Protocol")
            chosen = choose_subprotocol(offered)
            if chosen is None:
                self.refused += 1
                log.warning("%s: refused a WebSocket client from %s offering %s: it must offer %s", self.name, peer,
                            ", ".join(offered) or "no subprotocol", " or ".join(ACCEPTED))
                client.sendall(http_response("400 Bad Request", f"Offer the WebSocket subprotocol {' or '.join(ACCEPTED)}.\n"))
                return
            backend = self.open_backend()
            upstream = socket.create_connection(("127.0.0.1", backend.port), timeout=HANDSHAKE_TIMEOUT_S)
            if not self._track(upstream):
                return
            upstream.sendall(head.replace("Sec-WebSocket-Protocol", SDK_SUBPROTOCOL).encode() + rest)
            answer, rest = read_head(upstream)
            response = Head.parse(answer)
            if response.values("Sec-WebSocket-Protocol"):
                response = response.replace("Sec-WebSocket-Protocol", chosen)
            client.sendall(response.encode() + rest)
            if " 101 " not in response.start_line + " ":
                log.warning("%s: the server refused a client from %s: %s", self.name, peer, response.start_line)
                return
            self.connections += 1
            log.info("%s: client %s connected (subprotocol %s)", self.name, peer, chosen)
            client.settimeout(None)
            upstream.settimeout(None)
            copier = threading.Thread(target=_copy, args=(upstream, client), name=f"{self.name}-to-client", daemon=True)
            copier.start()
            _copy(client, upstream)
            copier.join()
        except (OSError, ValueError) as error:
            if not self._stopped.is_set():
                log.warning("%s: connection from %s ended: %s", self.name, peer, error)
        finally:
            for sock in (client, upstream):
                if sock is not None:
                    _close(sock)
                    with self._lock:
                        self._open.discard(sock)
            if backend is not None:
                backend.close()


def _copy(source: socket.socket, target: socket.socket) -> None:
    """Bytes from source to target until either side closes; then both are shut down, which
    ends the copy the other way too."""
    try:
        while True:
            data = source.recv(CHUNK)
            if not data:
                break
            target.sendall(data)
    except OSError:
        pass
    for sock in (source, target):
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass


def _close(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    sock.close()
