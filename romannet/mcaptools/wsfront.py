"""The public port of a Foxglove server: every subprotocol version the Foxglove app speaks, in front of the SDK.

The `foxglove-sdk` server (0.30) accepts only `foxglove.sdk.v1` / `foxglove.sdk.v1.1`; the current Foxglove app
offers those and `foxglove.websocket.v1`, while Foxglove Studio and Lichtblick offer `foxglove.websocket.v1`
alone, which the SDK answers with 400. Both names carry the same v1 messages (the ws-protocol spec), so this
front listens on the user's port, and for a client that offers only `foxglove.websocket.v1` it asks the SDK
(on a private loopback port) for `foxglove.sdk.v1` and answers the client with the name it offered; the
Sec-WebSocket-Accept depends on the key alone, so the handshake stays valid. After the handshake it copies
bytes both ways, untouched.
"""

from __future__ import annotations

import logging
import re
import socket
import threading

from romannet.common.errors import RomannetError

log = logging.getLogger(__name__)

SDK_PROTOCOLS = ("foxglove.sdk.v1.1", "foxglove.sdk.v1")  # what the SDK server accepts, newest first
LEGACY_PROTOCOL = "foxglove.websocket.v1"
_MAX_HEAD = 16384
_PROTOCOL_HEADER = re.compile(rb"(?im)^sec-websocket-protocol:[ \t]*([^\r\n]*)\r\n")


def offered(head: bytes) -> list[str]:
    """The subprotocols a client's upgrade request offers, in its order."""
    return [p.strip() for m in _PROTOCOL_HEADER.finditer(head) for p in m.group(1).decode("latin-1").split(",")
            if p.strip()]


def rewrite_request(head: bytes) -> tuple[bytes, str | None]:
    """(request for the SDK, the name to answer the client with instead of `foxglove.sdk.v1`, or None).

    A client offering an SDK name goes through as it is; one offering only the legacy name is asked for
    `foxglove.sdk.v1` and answered with `foxglove.websocket.v1`; any other goes through (the SDK refuses it)."""
    names = offered(head)
    if any(n in SDK_PROTOCOLS for n in names) or LEGACY_PROTOCOL not in names:
        return head, None
    return _PROTOCOL_HEADER.sub(b"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n", head, count=1), LEGACY_PROTOCOL


def rewrite_response(head: bytes, answer_as: str | None) -> bytes:
    if answer_as is None:
        return head
    return _PROTOCOL_HEADER.sub(f"sec-websocket-protocol: {answer_as}\r\n".encode(), head, count=1)


def bind_error(host: str, port: int, err: OSError) -> str:
    """One line for a port the server cannot listen on."""
    if err.errno in (98, 48, 10048):  # EADDRINUSE on Linux, macOS, Windows
        return (f"cannot serve Foxglove on {host}:{port}: the port is already in use (another process listens "
                "there: stop it or choose another --foxglove port)")
    return f"cannot serve Foxglove on {host}:{port}: {err.strerror or err}"


def _read_head(sock: socket.socket) -> bytes:
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = sock.recv(4096)
        if not chunk or len(head) > _MAX_HEAD:
            raise ConnectionError("no complete HTTP head")
        head += chunk
    return head


def _pump(src: socket.socket, dst: socket.socket) -> None:
    try:
        while chunk := src.recv(65536):
            dst.sendall(chunk)
    except OSError:
        pass
    finally:
        for s in (dst, src):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass


class ProtocolFront:
    """Listens on host:port (0: a free one, see .port) and hands each client to the SDK at 127.0.0.1:sdk_port."""

    def __init__(self, host: str, port: int, sdk_port: int):
        self.sdk_port = sdk_port
        self._sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._sock.bind((host, port))
        except OSError as err:
            self._sock.close()
            raise RomannetError(bind_error(host, port, err)) from None
        self._sock.listen(16)
        self.port = int(self._sock.getsockname()[1])
        self._closed = threading.Event()
        self._conns: set[socket.socket] = set()
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, name="foxglove-front", daemon=True).start()

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._sock.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), name="foxglove-conn", daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        upstream = None
        try:
            client.settimeout(10)
            head, rest = _read_head(client).split(b"\r\n\r\n", 1)
            request, answer_as = rewrite_request(head + b"\r\n\r\n")
            upstream = socket.create_connection(("127.0.0.1", self.sdk_port), timeout=10)
            upstream.sendall(request + rest)
            reply, after = _read_head(upstream).split(b"\r\n\r\n", 1)
            client.sendall(rewrite_response(reply + b"\r\n\r\n", answer_as) + after)
            client.settimeout(None)
            upstream.settimeout(None)
        except (OSError, ConnectionError) as err:
            log.debug("Foxglove client dropped during the handshake: %s", err)
            for s in (client, upstream):
                if s is not None:
                    s.close()
            return
        with self._lock:
            self._conns.update((client, upstream))
        back = threading.Thread(target=_pump, args=(upstream, client), daemon=True)
        back.start()
        _pump(client, upstream)
        back.join()
        with self._lock:
            self._conns.difference_update((client, upstream))
        client.close()
        upstream.close()

    def close(self) -> None:
        self._closed.set()
        try:
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the accept() under way (close alone does not)
        except OSError:
            pass
        self._sock.close()
        with self._lock:
            for s in self._conns:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()
