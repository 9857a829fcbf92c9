"""The live view: each actor's episode, as it is being written, served to the Foxglove app.

Actors already write every step to MCAP (actor/recorder.py flushes one chunk per step), so the live view
follows those files instead of reaching into the actor: the actor's decision path is untouched, and with no
client subscribed a poll costs a directory listing and a few record headers (chunks are skipped unread).
With a client, each new chunk is decoded and its messages are sent on `/<actor_id><topic>` with the schema
recorded in the file (camera, heightmaps, Q maps, /transition, /step, /tf, /camera/calibration).

Used by `romannet up --foxglove PORT` (a thread of the launcher, every actor of the run), `romannet actor
--foxglove PORT` (a thread beside the actor loop, that actor) and `romannet mcap live DIR --foxglove PORT`.
"""

from __future__ import annotations

import argparse
import io
import logging
import struct
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import EndOfFile
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from romannet.common.episode_file import ChannelInfo
from romannet.common.errors import RomannetError
from romannet.common.signals import stop_on_signals

from .foxglove_server import FoxgloveServer

log = logging.getLogger(__name__)

_MAGIC = b"\x89MCAP0\r\n"
_HEAD = struct.Struct("<BQ")
_OP_CHUNK, _OP_DATA_END = 0x06, 0x0F


@dataclass
class EpisodeTail:
    """Reads the whole records appended to one episode file since the last call (a record still being
    written is left for the next call)."""

    path: Path
    offset: int = len(_MAGIC)
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    finished: bool = False

    def _records(self, f: io.BufferedReader, size: int, decode: bool) -> Iterator[bytes]:
        """The bytes of each whole record from self.offset on; with decode False only those that are not
        chunks (so the channels are learnt while a chunk's messages, nobody's to see, stay unread)."""
        while not self.finished and self.offset + _HEAD.size <= size:
            f.seek(self.offset)
            opcode, length = _HEAD.unpack(f.read(_HEAD.size))
            end = self.offset + _HEAD.size + length
            if end > size:
                return
            if opcode == _OP_DATA_END:
                self.finished = True
            elif decode or opcode != _OP_CHUNK or not self.channels:
                f.seek(self.offset)
                yield f.read(end - self.offset)
            self.offset = end

    def read(self, decode: bool) -> list[tuple[ChannelInfo, Message]]:
        """New messages (with their channel), decoded only when `decode`; channels are learnt either way."""
        try:
            with open(self.path, "rb") as f:
                size = f.seek(0, io.SEEK_END)
                data = b"".join(self._records(f, size, decode))
        except OSError as err:
            log.debug("%s: %s", self.path, err)
            return []
        out = []
        for record in _decoded(data):
            if isinstance(record, Schema):
                self.schemas[record.id] = record
            elif isinstance(record, Channel) and record.schema_id in self.schemas:
                s = self.schemas[record.schema_id]
                self.channels[record.id] = ChannelInfo(record.topic, record.message_encoding, s.name, s.encoding,
                                                       s.data, dict(record.metadata))
            elif isinstance(record, Message) and decode and record.channel_id in self.channels:
                out.append((self.channels[record.channel_id], record))
        return out


def _decoded(data: bytes) -> Iterator[object]:
    """The records in `data` (whole records, chunks opened); the reader signals their end with EndOfFile."""
    try:
        yield from StreamReader(io.BytesIO(data), skip_magic=True).records
    except EndOfFile:
        return


def newest_episode(folder: Path) -> Path | None:
    files = sorted(folder.glob("ep*.mcap"))
    return files[-1] if files else None


class LiveView:
    """Serves the newest episode of each actor folder `watch()` returns ({actor_id: folder}) until close()."""

    def __init__(self, watch: Callable[[], dict[str, Path]], port: int, host: str = "127.0.0.1",
                 poll_s: float = 0.5, name: str = "romannet live"):
        self.server = FoxgloveServer(port, host=host, name=name)
        self._watch, self._poll_s = watch, poll_s
        self._tails: dict[str, EpisodeTail] = {}
        self._stop = threading.Event()
        self.sent = 0
        self._thread = threading.Thread(target=self._run, name="foxglove-live", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return self.server.port

    def _follow(self, actor_id: str, folder: Path) -> None:
        newest = newest_episode(folder)
        if newest is None:
            return
        tail = self._tails.get(actor_id)
        if tail is None or tail.path != newest:
            if tail is not None:  # the rest of the finished episode first
                self._send(actor_id, tail.read(self.server.listener.active > 0))
            # Joining mid-episode: its start is read (channels, first observation), never sent late.
            tail = self._tails[actor_id] = EpisodeTail(newest)
        self._send(actor_id, tail.read(self.server.listener.active > 0))

    def _send(self, actor_id: str, messages: list[tuple[ChannelInfo, Message]]) -> None:
        for channel, message in messages:
            topic = f"/{actor_id}{channel.topic}"
            self.server.add_channel(topic, channel)
            self.server.log(topic, message.data, message.log_time)
            self.sent += 1

    def _advertise(self) -> None:
        for actor_id, tail in self._tails.items():
            for channel in tail.channels.values():
                self.server.add_channel(f"/{actor_id}{channel.topic}", channel)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                for actor_id, folder in sorted(self._watch().items()):
                    self._follow(actor_id, folder)
                self._advertise()
            except Exception:  # the view must never take its host process down
                log.exception("live view: reading the episodes failed; trying again")
            self._stop.wait(self._poll_s)

    def follow(self, watch: Callable[[], dict[str, Path]]) -> None:
        """Serve the folders `watch()` returns from now on (a view opened before its run directory existed)."""
        self._watch = watch

    def close(self) -> None:
        self._stop.set()
        self._thread.join(10)
        self.server.close()


def run_folders(episodes_root: Path) -> Callable[[], dict[str, Path]]:
    """Every actor folder under a run's episodes/ directory, as they appear."""
    return lambda: {p.name: p for p in episodes_root.iterdir() if p.is_dir()} if episodes_root.is_dir() else {}


def start_live_view(watch: Callable[[], dict[str, Path]], port: int, host: str, what: str) -> LiveView:
    view = LiveView(watch, port, host)
    announce_live_view(view, host, what)
    return view


def announce_live_view(view: LiveView, host: str, what: str) -> None:
    log.info("live view of %s on ws://%s:%d (Foxglove app: Open connection -> Foxglove WebSocket), or %s", what,
             host, view.port, view.server.app_url())


def run_live(args: argparse.Namespace) -> int:
    """`romannet mcap live DIR --foxglove PORT`: until Ctrl-C."""
    folder = Path(args.folder)
    if args.foxglove is None:
        raise RomannetError("nothing to serve to: pass --foxglove PORT")
    if not folder.is_dir():
        raise RomannetError(f"{folder}: no such directory (a run's episodes/ or one actor's folder in it)")
    one_actor = any(folder.glob("ep*.mcap")) or folder.parent.name == "episodes"
    watch = (lambda: {folder.name: folder}) if one_actor else run_folders(folder)
    stop = threading.Event()
    with stop_on_signals(stop, "stopping the live view"):
        view = start_live_view(watch, args.foxglove, args.foxglove_host, str(folder))
        try:
            stop.wait()
        finally:
            view.close()
    sys.stdout.write(f"live view of {folder} stopped after {view.sent} messages\n")
    return 0
