"""Reading the actor's MCAP episode files, also unfinished ones, with one typed error for files that are not.

    reader = EpisodeReader("runs/r1/episodes/actor-0/ep000003.mcap")  # NotMcapError if it is not MCAP
    for msg in reader.messages({TRANSITION_TOPIC}):                     # file order, whole records only
        ...msg.data...                                                  # the bytes the actor sent to replay
    reader.health                                                       # complete? how much was read?

The file is read front to back record by record (no seeking, no summary needed), so a file whose writer
died (no summary, no footer, a torn last chunk) yields everything up to its last whole chunk, and
`health` says where and why reading stopped. Each chunk's CRC is checked; a damaged chunk ends the read
like a torn one. Nothing here unpickles: messages stay bytes (protobuf / JSON), decoded by the caller
with the validating decoders of common.wire.

A file that is not an episode raises one EpisodeFileError subclass whose message starts with the path:
NotMcapError (no MCAP magic, empty, unreadable) or ForeignMcapError (a channel with a schema episode
files never use, /transition with another schema, or no "romannet" metadata record before the first
chunk: the actor writes that record before any message). The format is documented in docs/recording.md.
"""

from __future__ import annotations

import io
import logging
import struct
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.records import Attachment, Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk

from .errors import RomannetError

log = logging.getLogger(__name__)

# Topics of an episode file (actor/recorder.py writes them; docs/recording.md describes them).
CAMERA_COLOR_TOPIC = "/camera/color"
CAMERA_DEPTH_TOPIC = "/camera/depth"
HEIGHTMAP_COLOR_TOPIC = "/heightmap/color"
HEIGHTMAP_DEPTH_TOPIC = "/heightmap/depth"
Q_TOPIC_PREFIX = "/q/"
TRANSITION_TOPIC = "/transition"
STEP_TOPIC = "/step"
OBSERVATION_TOPICS = (HEIGHTMAP_COLOR_TOPIC, HEIGHTMAP_DEPTH_TOPIC, CAMERA_COLOR_TOPIC, CAMERA_DEPTH_TOPIC)
TRANSITION_SCHEMA = "romannet.v1.Transition"
STEP_SCHEMA = "romannet.actor.Step"
# (schema name, schema encoding) of every channel an episode file may hold.
KNOWN_SCHEMAS = frozenset({("foxglove.CompressedImage", "protobuf"), ("foxglove.RawImage", "protobuf"),
                           (TRANSITION_SCHEMA, "protobuf"), (STEP_SCHEMA, "jsonschema")})
EPISODE_METADATA = "romannet"  # run id, actor id, episode id, task, seed, weights version, units
CONFIG_METADATA = "config"  # {"toml": the resolved config}
END_METADATA = "episode_end"  # done reason, steps, efficiency, weights version at the end
MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_OP_ATTACHMENT, _OP_METADATA, _OP_DATA_END = 0x09, 0x0C, 0x0F
_RECORD_HEADER = struct.Struct("<BQ")


class EpisodeFileError(RomannetError):
    """A file is not a readable RoManNet episode; the message starts with its path."""

    def __init__(self, path: str | Path, problem: str):
        self.path, self.problem = Path(path), problem
        super().__init__(f"{path}: {problem}")


class NotMcapError(EpisodeFileError):
    """The file is not MCAP at all (no magic bytes), empty, missing or unreadable."""


class ForeignMcapError(EpisodeFileError):
    """The file is MCAP but not an episode written by a RoManNet actor (foreign schemas or metadata)."""


@dataclass(frozen=True)
class ChannelInfo:
    """A channel with its schema, as declared in the file."""

    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    metadata: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class RecordedMessage:
    """One message as recorded. end_offset: bytes of the file read once it was available (progress)."""

    topic: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes
    end_offset: int


@dataclass(frozen=True)
class FileHealth:
    """How a read went: complete (summary and footer present) or where and why it stopped."""

    complete: bool
    file_bytes: int
    read_bytes: int  # up to the end of the last whole record of the data section
    problem: str = ""  # why reading stopped early ("" when complete)

    @property
    def recovered_fraction(self) -> float:
        return self.read_bytes / self.file_bytes if self.file_bytes else 0.0

    def describe(self) -> str:
        if self.complete:
            return "complete"
        if self.read_bytes and "summary or footer" in self.problem:
            return f"truncated after the data: all messages read; {self.problem}"
        return (f"truncated: read {self.read_bytes} of {self.file_bytes} bytes "
                f"({100 * self.recovered_fraction:.0f} %), up to the last whole chunk; {self.problem}")


class _Stop(Exception):
    """Reading ends here: the file is torn or damaged at this point (not an error of the caller)."""


class EpisodeReader:
    """One episode file, read front to back; see the module docstring."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: list[tuple[str, str, bytes]] = []  # (name, media type, data)
        self.channels: dict[int, ChannelInfo] = {}
        self.health: FileHealth | None = None  # set when messages() has run to its end
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        try:
            self.file_bytes = self.path.stat().st_size
            with open(self.path, "rb") as f:
                head = f.read(len(MCAP_MAGIC))
        except FileNotFoundError:
            raise NotMcapError(self.path, "no such file") from None
        except OSError as err:
            raise NotMcapError(self.path, f"cannot be read ({err.strerror or err})") from None
        if self.path.is_dir():
            raise NotMcapError(self.path, "is a directory")
        if head != MCAP_MAGIC:
            shown = "it is empty" if not head else f"it starts with {head[:8]!r}"
            raise NotMcapError(self.path, f"not an MCAP file ({shown}, not the MCAP magic bytes)")

    @property
    def episode(self) -> dict[str, str]:
        """The "romannet" metadata record (run id, actor id, episode id, task, seed, ...)."""
        return self.metadata.get(EPISODE_METADATA, {})

    @property
    def config_toml(self) -> str:
        return self.metadata.get(CONFIG_METADATA, {}).get("toml", "")

    def channel_by_topic(self, topic: str) -> ChannelInfo | None:
        return next((c for c in self.channels.values() if c.topic == topic), None)

    # ------------------------------------------------------------------------------------- reading
    def messages(self, topics: Collection[str] | None = None) -> Iterator[RecordedMessage]:
        """Messages in file order (for an episode: recorded order), only of `topics` if given."""
        wanted = None if topics is None else set(topics)
        read_to, problem, complete = len(MCAP_MAGIC), "", False
        with open(self.path, "rb") as f:
            f.seek(read_to)
            try:
                for opcode, body, end in self._records(f, read_to):
                    if opcode == _OP_DATA_END:
                        read_to = end
                        complete = self._has_footer(f, end)
                        problem = "" if complete else "the summary or footer after the data is damaged"
                        break
                    yield from self._handle(opcode, body, end, wanted)
                    read_to = end
                else:
                    problem = "the file ends without a summary or footer (the writer did not finish it)"
            except _Stop as stop:
                problem = str(stop)
        self.health = FileHealth(complete, self.file_bytes, read_to, problem)
        if complete:
            self._require_episode()  # a finished MCAP file without the actor's metadata is not an episode
        else:
            log.debug("%s: %s", self.path, self.health.describe())

    def _records(self, f: io.BufferedReader, offset: int) -> Iterator[tuple[int, bytes, int]]:
        """(opcode, body, end offset) of each whole record from offset on; _Stop at a torn record."""
        while offset < self.file_bytes:
            header = f.read(_RECORD_HEADER.size)
            if len(header) < _RECORD_HEADER.size:
                raise _Stop(f"the file ends inside a record header at byte {offset}")
            opcode, length = _RECORD_HEADER.unpack(header)
            if offset == len(MCAP_MAGIC) and opcode != _OP_HEADER:
                raise NotMcapError(self.path, "not an MCAP file (the MCAP magic bytes are not followed by a "
                                   "Header record)")
            end = offset + _RECORD_HEADER.size + length
            if end > self.file_bytes:
                raise _Stop(f"the file ends inside a {_op_name(opcode)} record that starts at byte {offset} "
                            f"({self.file_bytes - offset} of {end - offset} bytes present)")
            body = f.read(length)
            if len(body) != length:
                raise _Stop(f"short read inside the record at byte {offset}")
            yield opcode, body, end
            offset = end

    def _handle(self, opcode: int, body: bytes, end: int, wanted: set[str] | None) -> Iterator[RecordedMessage]:
        stream = ReadDataStream(io.BytesIO(body))
        if opcode in (_OP_CHUNK, _OP_MESSAGE, _OP_CHANNEL):
            self._require_episode()
        if opcode == _OP_CHUNK:
            try:
                records = breakup_chunk(Chunk.read(stream), validate_crc=True)
            except Exception as err:  # CRC mismatch, bad compression: the chunk is damaged
                raise _Stop(f"the chunk ending at byte {end} is damaged ({type(err).__name__}: {err})") from None
            for record in records:
                if isinstance(record, Message):
                    yield from self._message(record, end, wanted)
                elif isinstance(record, Schema):
                    self._schema(record)
                elif isinstance(record, Channel):
                    self._channel(record)
        elif opcode == _OP_MESSAGE:
            yield from self._message(Message.read(stream, len(body)), end, wanted)
        elif opcode == _OP_SCHEMA:
            self._schema(Schema.read(stream))
        elif opcode == _OP_CHANNEL:
            self._channel(Channel.read(stream))
        elif opcode == _OP_METADATA:
            meta = Metadata.read(stream)
            self.metadata[meta.name] = dict(meta.metadata)
        elif opcode == _OP_ATTACHMENT:
            att = Attachment.read(stream)
            self.attachments.append((att.name, att.media_type, bytes(att.data)))
        # Header, message indexes and anything unknown carry nothing an episode reader needs.

    def _require_episode(self) -> None:
        """The actor writes its metadata record before any channel or message."""
        if EPISODE_METADATA not in self.metadata:
            raise ForeignMcapError(self.path, f"no '{EPISODE_METADATA}' metadata record before the first "
                                   "message: not an episode written by a RoManNet actor")

    def _schema(self, schema: Schema) -> None:
        self._schemas[schema.id] = (schema.name, schema.encoding, bytes(schema.data))

    def _channel(self, channel: Channel) -> None:
        if channel.id in self.channels:
            return
        name, encoding, data = self._schemas.get(channel.schema_id, ("", "", b""))
        if (name, encoding) not in KNOWN_SCHEMAS:
            shown = f"schema {name!r} ({encoding})" if name else "no schema"
            raise ForeignMcapError(self.path, f"channel {channel.topic!r} has {shown}, which RoManNet episode "
                                   f"files never use (they hold {', '.join(sorted(n for n, _ in KNOWN_SCHEMAS))})")
        if channel.topic == TRANSITION_TOPIC and name != TRANSITION_SCHEMA:
            raise ForeignMcapError(self.path, f"channel {TRANSITION_TOPIC!r} has schema {name!r}, not "
                                   f"{TRANSITION_SCHEMA!r}")
        self.channels[channel.id] = ChannelInfo(channel.topic, channel.message_encoding, name, encoding, data,
                                                dict(channel.metadata))

    def _message(self, message: Message, end: int, wanted: set[str] | None) -> Iterator[RecordedMessage]:
        channel = self.channels.get(message.channel_id)
        if channel is None:
            raise _Stop(f"a message before the end of byte {end} names unknown channel {message.channel_id}")
        if wanted is None or channel.topic in wanted:
            yield RecordedMessage(channel.topic, message.log_time, message.publish_time, message.sequence,
                                  bytes(message.data), end)

    def _has_footer(self, f: io.BufferedReader, offset: int) -> bool:
        """True if the summary records after DataEnd lead to a Footer and the closing magic."""
        try:
            for opcode, body, end in self._records(f, offset):
                if opcode == _OP_FOOTER:
                    Footer.read(ReadDataStream(io.BytesIO(body)))
                    f.seek(end)
                    return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
        except Exception:  # a torn or damaged summary: the data was read all the same
            return False
        return False


def _op_name(opcode: int) -> str:
    names = {_OP_HEADER: "Header", _OP_CHUNK: "Chunk", _OP_MESSAGE: "Message", _OP_METADATA: "Metadata",
             _OP_ATTACHMENT: "Attachment", _OP_SCHEMA: "Schema", _OP_CHANNEL: "Channel"}
    return names.get(opcode, f"opcode-0x{opcode:02x}")


@dataclass(frozen=True)
class Episode:
    """A whole episode file in memory (only the topics asked for)."""

    path: Path
    metadata: dict[str, dict[str, str]]
    channels: tuple[ChannelInfo, ...]
    messages: tuple[RecordedMessage, ...]
    health: FileHealth
    attachments: tuple[tuple[str, str, bytes], ...] = ()

    @property
    def episode(self) -> dict[str, str]:
        return self.metadata.get(EPISODE_METADATA, {})

    @property
    def config_toml(self) -> str:
        return self.metadata.get(CONFIG_METADATA, {}).get("toml", "")

    def of(self, topic: str) -> list[RecordedMessage]:
        return [m for m in self.messages if m.topic == topic]


def read_episode(path: str | Path, topics: Collection[str] | None = None) -> Episode:
    """Read a whole episode file (see EpisodeReader); `topics` limits what is kept in memory."""
    reader = EpisodeReader(path)
    messages = tuple(reader.messages(topics))
    assert reader.health is not None
    return Episode(reader.path, reader.metadata, tuple(reader.channels.values()), messages, reader.health,
                   tuple(reader.attachments))


def episode_paths(inputs: Sequence[str | Path]) -> list[Path]:
    """The files named by FILE|DIR arguments: a file as given, a directory's *.mcap (recursively, sorted).

    Raises NotMcapError for a path that does not exist or a directory without .mcap files."""
    out: list[Path] = []
    for item in inputs:
        path = Path(item)
        if path.is_dir():
            found = sorted(p for p in path.rglob("*.mcap") if p.is_file())
            if not found:
                raise NotMcapError(path, "the directory holds no .mcap files")
            out += found
        elif path.exists():
            out.append(path)
        else:
            raise NotMcapError(path, "no such file or directory")
    return list(dict.fromkeys(out))  # each file once, in order
