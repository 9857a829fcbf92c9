"""Where `romannet mcap play` sends recorded messages: a Foxglove WebSocket server and/or Zenoh.

FoxgloveSink: a live Foxglove WebSocket server (foxglove_server.py: the `foxglove-sdk` package behind a
front that speaks every protocol version the app offers) advertising every channel of the episode with the
schema recorded in the file, so the Foxglove app decodes the images and the
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
from typing import Protocol

import zenoh

from romannet.common.episode_file import ChannelInfo, RecordedMessage
from romannet.common.keys import RunKeys

log = logging.getLogger(__name__)

_POLL_S = 0.02


class Sink(Protocol):
    def send(self, msg: RecordedMessage) -> None: ...

    def close(self) -> None: ...


class FoxgloveSink:
    """A Foxglove WebSocket server on host:port (port 0: any free port, see .port) with every channel of
    the episode advertised (foxglove_server.FoxgloveServer: every protocol version the app speaks)."""

    def __init__(self, channels: Iterable[ChannelInfo], port: int, host: str = "127.0.0.1",
                 name: str = "romannet mcap play"):
        from .foxglove_server import FoxgloveServer  # imported here: only `play --foxglove` needs the SDK

        self.server = FoxgloveServer(port, host=host, name=name)
        for c in channels:
            self.server.add_channel(c.topic, c)

    @property
    def port(self) -> int:
        return self.server.port

    def app_url(self) -> str:
        return self.server.app_url()

    def wait_for_client(self, timeout_s: float | None, stop: threading.Event, grace_s: float = 1.0) -> bool:
        return self.server.wait_for_client(timeout_s, stop, grace_s)

    def send(self, msg: RecordedMessage) -> None:
        self.server.log(msg.topic, msg.data, msg.log_time_ns)

    def close(self) -> None:
        self.server.close()


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
