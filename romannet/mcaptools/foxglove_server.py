"""A Foxglove WebSocket server for `mcap play` and the live view: the `foxglove-sdk` server on a private
loopback port behind wsfront.ProtocolFront on the user's port, so every protocol version the app offers
is served (see wsfront). Channels carry the schemas recorded in the episodes, so the app decodes them as
when it opens the file. The SDK is imported here only: the commands without --foxglove never load it.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from romannet.common.episode_file import ChannelInfo
from romannet.common.errors import RomannetError

from .wsfront import ProtocolFront

log = logging.getLogger(__name__)


class Subscriptions:
    """foxglove.websocket.ServerListener: how many subscriptions clients hold now, and whether one ever did."""

    def __init__(self) -> None:
        self.first = threading.Event()
        self.active = 0
        self._lock = threading.Lock()

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            self.active += 1
        log.info("Foxglove client %s subscribed to %s", client.id, channel.topic)
        self.first.set()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            self.active = max(0, self.active - 1)
        log.debug("Foxglove client %s unsubscribed from %s", client.id, channel.topic)


def foxglove_start_error(host: str, port: int, text: str) -> str:
    """One line for a Foxglove server that could not start (text: the SDK's error)."""
    if "Address already in use" in text:
        return (f"cannot serve Foxglove on {host}:{port}: the port is already in use (another process listens "
                "there: stop it or choose another --foxglove port)")
    return f"cannot serve Foxglove on {host}:{port}: {text.removeprefix('FoxgloveError: ')}"


class FoxgloveServer:
    """Serves on host:port (0: any free port, see .port) until close()."""

    def __init__(self, port: int, host: str = "127.0.0.1", name: str = "romannet"):
        import foxglove
        from foxglove.websocket import Capability

        self._foxglove = foxglove
        self.context = foxglove.Context()
        self.listener = Subscriptions()
        try:
            self._server = foxglove.start_server(name=name, host="127.0.0.1", port=0, context=self.context,
                                                 capabilities=[Capability.Time], server_listener=self.listener)
        except RuntimeError as exc:  # the SDK's FoxgloveError
            raise RomannetError(foxglove_start_error(host, port, str(exc))) from None
        try:
            self._front = ProtocolFront(host, port, int(self._server.port))
        except RomannetError:
            self._server.stop()
            raise
        self.channels: dict[str, Any] = {}

    @property
    def port(self) -> int:
        return self._front.port

    def app_url(self) -> str:
        return f"https://app.foxglove.dev/~/view?ds=foxglove-websocket&ds.url=ws://127.0.0.1:{self.port}"

    def add_channel(self, topic: str, c: ChannelInfo) -> Any:
        """The channel `topic` with the schema and encoding of recorded channel `c` (made once)."""
        if topic not in self.channels:
            schema = self._foxglove.Schema(name=c.schema_name, encoding=c.schema_encoding, data=c.schema_data)
            self.channels[topic] = self._foxglove.Channel(topic, schema=schema, message_encoding=c.message_encoding,
                                                          context=self.context, metadata=dict(c.metadata))
        return self.channels[topic]

    def log(self, topic: str, data: bytes, log_time_ns: int) -> None:
        channel = self.channels.get(topic)
        if channel is not None:
            self._server.broadcast_time(log_time_ns)
            channel.log(data, log_time=log_time_ns)

    def wait_for_client(self, timeout_s: float | None, stop: threading.Event, grace_s: float = 1.0) -> bool:
        """Wait until a client subscribes to a channel (then `grace_s` more for its other subscriptions);
        False after timeout_s (None: until stop) without one."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self.listener.first.wait(0.1):
            if stop.is_set() or (deadline is not None and time.monotonic() > deadline):
                return False
        stop.wait(grace_s)
        return True

    def close(self) -> None:
        for channel in self.channels.values():
            channel.close()
        self._front.close()
        self._server.stop()
