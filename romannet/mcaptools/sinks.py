"""Where `romannet mcap play` sends recorded messages: a Foxglove WebSocket server and/or Zenoh.

FoxgloveSink: a live Foxglove WebSocket server (the `foxglove-sdk` package) advertising every channel of
the episode with the schema recorded in the file, so the Foxglove app decodes the images and the
Transition exactly as when it opens the file; the server announces each message's recorded time (Time
capability), so the app's clock follows the recording.

ZenohSink: one publisher per topic on `romannet/@v1/<run>/actor/<actor_id>/live/<topic>` (common/keys.py),
payload = the recorded bytes, encoding = protobuf or JSON with the schema name, attachment = UTF-8 JSON
{"log_time_ns", "publish_time_ns", "sequence"} of the recording. Congestion control BLOCK: nothing is
dropped, and a session delivers its puts in order, so subscribers see the recorded order.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterable
from typing import Any, Protocol

import zenoh

from romannet.common.episode_file import ChannelInfo, RecordedMessage
from romannet.common.errors import RomannetError
from romannet.common.keys import RunKeys

log = logging.getLogger(__name__)

_POLL_S = 0.02


class Sink(Protocol):
    def send(self, msg: RecordedMessage) -> None: ...

    def close(self) -> None: ...


class _Subscriptions:
    """foxglove.websocket.ServerListener: notes that some client subscribed to some channel."""

    def __init__(self) -> None:
        self.first = threading.Event()
        self.count = 0

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.count += 1
        log.info("Foxglove client %s subscribed to %s", client.id, channel.topic)
        self.first.set()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        log.debug("Foxglove client %s unsubscribed from %s", client.id, channel.topic)


def foxglove_start_error(host: str, port: int, text: str) -> str:
    """One line for a Foxglove server that could not start (text: the SDK's error)."""
    if "Address already in use" in text:
        return (f"cannot serve Foxglove on {host}:{port}: the port is already in use (another process listens "
                "there: stop it or choose another --foxglove port)")
    return f"cannot serve Foxglove on {host}:{port}: {text.removeprefix('FoxgloveError: ')}"


class FoxgloveSink:
    """A Foxglove WebSocket server on host:port (port 0: any free port, see .port)."""

    def __init__(self, channels: Iterable[ChannelInfo], port: int, host: str = "127.0.0.1",
                 name: str = "romannet mcap play"):
        import foxglove  # imported here: only `play --foxglove` needs the SDK
        from foxglove.websocket import Capability

        self._context = foxglove.Context()
        self._listener = _Subscriptions()
        try:
            self._server = foxglove.start_server(name=name, host=host, port=port, context=self._context,
                                                 capabilities=[Capability.Time], server_listener=self._listener)
        except RuntimeError as exc:  # the SDK's FoxgloveError, e.g. "Failed to bind port: Address already in use"
            raise RomannetError(foxglove_start_error(host, port, str(exc))) from None
        self._channels = {}
        for c in channels:
            schema = foxglove.Schema(name=c.schema_name, encoding=c.schema_encoding, data=c.schema_data)
            self._channels[c.topic] = foxglove.Channel(c.topic, schema=schema, message_encoding=c.message_encoding,
                                                       context=self._context, metadata=dict(c.metadata))

    @property
    def port(self) -> int:
        return int(self._server.port)

    def app_url(self) -> str:
        return self._server.app_url() or f"ws://127.0.0.1:{self.port}"

    def wait_for_client(self, timeout_s: float | None, stop: threading.Event, grace_s: float = 1.0) -> bool:
        """Wait until a client subscribes to a channel (then `grace_s` more for its other subscriptions);
        False after timeout_s (None: until stop) without one."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._listener.first.wait(_POLL_S * 5):
            if stop.is_set() or (deadline is not None and time.monotonic() > deadline):
                return False
        stop.wait(grace_s)
        return True

    def send(self, msg: RecordedMessage) -> None:
        channel = self._channels.get(msg.topic)
        if channel is None:  # a channel the pre-scan did not see cannot appear; be safe anyway
            return
        self._server.broadcast_time(msg.log_time_ns)
        channel.log(msg.data, log_time=msg.log_time_ns)

    def close(self) -> None:
        for channel in self._channels.values():
            channel.close()
        self._server.stop()


def encoding_of(channel: ChannelInfo) -> zenoh.Encoding:
    """The Zenoh encoding of a channel's messages: protobuf or JSON, with the schema name."""
    base = zenoh.Encoding.APPLICATION_PROTOBUF if channel.message_encoding == "protobuf" else \
        zenoh.Encoding.APPLICATION_JSON
    return base.with_schema(channel.schema_name)


def attachment_of(msg: RecordedMessage) -> bytes:
    return json.dumps({"log_time_ns": msg.log_time_ns, "publish_time_ns": msg.publish_time_ns,
                       "sequence": msg.sequence}).encode()


class ZenohSink:
    """Publishers on the live keys of `actor_id` in run `run_id` (see the module docstring)."""

    def __init__(self, session: zenoh.Session, run_id: str, actor_id: str, channels: Iterable[ChannelInfo]):
        keys = RunKeys(run_id)
        self.publishers = {
            c.topic: session.declare_publisher(keys.actor_live(actor_id, c.topic), encoding=encoding_of(c),
                                               congestion_control=zenoh.CongestionControl.BLOCK,
                                               reliability=zenoh.Reliability.RELIABLE)
            for c in channels}
        self.key_prefix = keys.actor_live(actor_id, "x").rsplit("/", 1)[0]

    def wait_for_subscribers(self, timeout_s: float, stop: threading.Event) -> bool:
        """True once some subscriber matches one of the publishers (declarations take a moment to arrive
        after a session connects); False after timeout_s without one."""
        deadline = time.monotonic() + timeout_s
        while not any(p.matching_status.matching for p in self.publishers.values()):
            if stop.is_set() or time.monotonic() > deadline:
                return False
            time.sleep(_POLL_S)
        return True

    def send(self, msg: RecordedMessage) -> None:
        publisher = self.publishers.get(msg.topic)
        if publisher is not None:
            publisher.put(msg.data, attachment=attachment_of(msg))

    def close(self) -> None:
        for publisher in self.publishers.values():
            publisher.undeclare()
