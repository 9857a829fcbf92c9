"""Reading the actor's MCAP episode files, also unfinished or damaged ones, with one typed error for files
that are not episodes at all.

    reader = EpisodeReader("runs/r1/episodes/actor-0/ep000003.mcap")  # NotMcapError if it is not MCAP
    for msg in reader.messages({TRANSITION_TOPIC}):                     # file order, whole records only
        ...msg.data...                                                  # the bytes the actor sent to replay
    reader.health                                                       # complete? damaged? how much read?

The file is read front to back record by record, so a file whose writer died (no summary, no footer, a
torn last chunk) yields everything up to its last whole chunk, and `health.problem` says where and why
reading stopped. Damage in the middle costs only the damaged part, and `health.damage` names each one:

- a chunk whose CRC does not match (or that does not decompress) is skipped, reading goes on after it;
- a record whose header is damaged (its length or opcode) breaks the framing: reading resumes at the next
  whole record, found through the summary's chunk and metadata indexes when the summary is intact, else
  by scanning for the next chunk whose lengths add up and whose CRC matches;
- a metadata record that does not parse is skipped; a changed byte inside a metadata value that still
  parses is seen only through the CRC over the whole data section, which the writer may leave out (0);
- messages of channels whose declaration was in a skipped chunk are read through the copies of every
  channel in the summary; without a summary they cannot be read and are counted;
- a summary whose CRC does not match, or a damaged footer, is named; the data is read all the same.

Nothing here unpickles: messages stay bytes (protobuf / JSON), decoded by the caller with the validating
decoders of common.wire.

A file that is not an episode raises one EpisodeFileError subclass whose message starts with the path:
NotMcapError (no MCAP magic, empty, unreadable) or ForeignMcapError (a channel with a schema episode
files never use, /transition with another schema, or no "romannet" metadata record before the first
chunk: the actor writes that record before any message). The format is documented in docs/recording.md.
"""

from __future__ import annotations

import io
import logging
import re
import struct
import zlib
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    ChunkIndex,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
)
from mcap.stream_reader import CRCValidationError, breakup_chunk

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
_OP_CHUNK_INDEX, _OP_ATTACHMENT, _OP_STATISTICS, _OP_METADATA, _OP_METADATA_INDEX, _OP_DATA_END = (
    0x08, 0x09, 0x0B, 0x0C, 0x0D, 0x0F)
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
    """How a read went: complete (summary and footer present), damaged (parts skipped, each named in
    `damage`) and/or ended early (`problem` says where and why)."""

    complete: bool
    file_bytes: int
    read_bytes: int  # up to the end of the last record read (of the data section)
    problem: str = ""  # why reading stopped before the summary ("" when it got there)
    damage: tuple[str, ...] = ()  # each damaged part that was skipped, with where it is
    skipped_bytes: int = 0  # of damaged chunks and of bytes between a broken record and the next whole one
    expected: dict[str, int] = field(default_factory=dict)  # messages per topic by the summary's statistics

    @property
    def damaged(self) -> bool:
        return bool(self.damage)

    @property
    def state(self) -> str:
        """'damaged' (something in the file is broken), 'truncated' (it ends early) or 'complete'."""
        return "damaged" if self.damage else ("complete" if self.complete else "truncated")

    @property
    def recovered_fraction(self) -> float:
        return (self.read_bytes - self.skipped_bytes) / self.file_bytes if self.file_bytes else 0.0

    def describe(self) -> str:
        """One line for people."""
        parts = []
        if self.damage:
            shown = "; ".join(self.damage[:3]) + (f"; and {len(self.damage) - 3} more" if len(self.damage) > 3 else "")
            parts.append(f"damaged: {shown}")
        if self.complete:
            return parts[0] if parts else "complete"
        if self.read_bytes and "summary or footer" in self.problem:
            parts.append(f"truncated after the data: all messages read; {self.problem}")
        else:
            parts.append(f"truncated: read {self.read_bytes} of {self.file_bytes} bytes "
                         f"({100 * self.read_bytes / max(self.file_bytes, 1):.0f} %), up to the last whole chunk; "
                         f"{self.problem}")
        return "; ".join(parts)


class _Stop(Exception):
    """Reading ends here: the file is torn at this point and nothing whole follows (not an error of the caller)."""


@dataclass
class _Summary:
    """What an intact summary section offers a reader of a damaged file."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    resume_at: list[int] = field(default_factory=list)  # record starts: chunks, metadata, DataEnd
    metadata_names: dict[int, str] = field(default_factory=dict)  # record start -> metadata name
    data_end: int = 0  # where the DataEnd record starts
    message_counts: dict[int, int] = field(default_factory=dict)  # channel id -> messages written


_KNOWN_OPCODES = frozenset(range(0x01, 0x11))  # Header .. DataEnd in the MCAP specification
_COMPRESSIONS = frozenset({"", "zstd", "lz4"})
_FOOTER_TAIL = _RECORD_HEADER.size + 20 + len(MCAP_MAGIC)  # Footer record (20-byte body), closing magic
_SCAN_BLOCK = 1 << 20
_CANDIDATE = re.compile(rb"[\x06\x0c]")  # where a Chunk or Metadata record may start
_MAX_SCANNED_METADATA = 64 << 20  # a metadata record longer than this found by scanning is not believed


def chunk_fits(head: bytes, length: int) -> bool:
    """True if a Chunk record body of `length` bytes starting with `head` (its first 64 bytes or all of
    them) has lengths that add up: times, sizes and CRC (32 bytes), compression name, records length and
    the records fill the record exactly. A flipped byte in a record length breaks this."""
    if len(head) < 40 or length < 40:
        return False
    name_len = int.from_bytes(head[28:32], "little")
    if name_len > 16 or 40 + name_len > len(head):
        return False
    try:
        compression = head[32:32 + name_len].decode()
    except UnicodeDecodeError:
        return False
    records = int.from_bytes(head[32 + name_len:40 + name_len], "little")
    return compression in _COMPRESSIONS and 40 + name_len + records == length


def parse_metadata(body: bytes) -> Metadata | None:
    """A Metadata record body parsed, None unless it parses and fills its record exactly."""
    stream = ReadDataStream(io.BytesIO(body))
    try:
        meta = Metadata.read(stream)
    except Exception:  # struct.error, UnicodeDecodeError, EndOfFile: the bytes are not a metadata record
        return None
    return meta if stream.count == len(body) else None


def parse_summary(data: bytes, summary_start: int) -> _Summary:
    """The records of a summary section (the bytes from its start to the Footer) in a _Summary."""
    out = _Summary(data_end=summary_start - _RECORD_HEADER.size - 4)
    offset = 0
    while offset + _RECORD_HEADER.size <= len(data):
        opcode, length = _RECORD_HEADER.unpack_from(data, offset)
        body = data[offset + _RECORD_HEADER.size:offset + _RECORD_HEADER.size + length]
        offset += _RECORD_HEADER.size + length
        stream = ReadDataStream(io.BytesIO(body))
        if opcode == _OP_SCHEMA:
            schema = Schema.read(stream)
            out.schemas[schema.id] = schema
        elif opcode == _OP_CHANNEL:
            channel = Channel.read(stream)
            out.channels[channel.id] = channel
        elif opcode == _OP_CHUNK_INDEX:
            out.resume_at.append(ChunkIndex.read(stream).chunk_start_offset)
        elif opcode == _OP_METADATA_INDEX:
            index = MetadataIndex.read(stream)
            out.resume_at.append(index.offset)
            out.metadata_names[index.offset] = index.name
        elif opcode == _OP_STATISTICS:
            out.message_counts = dict(Statistics.read(stream).channel_message_counts)
    out.resume_at = sorted({*out.resume_at, out.data_end})
    return out


class EpisodeReader:
    """One episode file, read front to back; see the module docstring."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: list[tuple[str, str, bytes]] = []  # (name, media type, data)
        self.channels: dict[int, ChannelInfo] = {}
        self.health: FileHealth | None = None  # set when messages() has run to its end
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        self._summary: _Summary | None = None
        self._damage: list[str] = []
        self._skipped = 0
        self._good_until = len(MCAP_MAGIC)  # end of the last record known whole (CRC, exact parse)
        self._lost_messages = 0  # of channels declared only in a skipped chunk
        self._data_crc = 0  # over the records read so far, for the DataEnd record's CRC
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
        self._damage, self._skipped, self._lost_messages = [], 0, 0
        self._good_until, self._summary = len(MCAP_MAGIC), None
        self._data_crc = zlib.crc32(MCAP_MAGIC)
        try:
            with open(self.path, "rb") as f:
                footer_ok = self._read_summary(f)
                for opcode, body, start, end in self._records(f):
                    if opcode == _OP_DATA_END:
                        self._check_data_crc(body)
                        read_to = end
                        complete = footer_ok is not None  # a damaged summary is named in the damage
                        if footer_ok is None:
                            problem = "the summary or footer after the data is missing (cut or zeroed)"
                        break
                    yield from self._handle(opcode, body, start, end, wanted)
                    read_to = end
                else:
                    problem = "the file ends without a summary or footer (the writer did not finish it)"
        except _Stop as stop:
            problem = str(stop)
        except OSError as err:  # a failing disk: what was read stands, the rest is named
            problem = f"reading failed after byte {read_to} ({err.strerror or err})"
        if self._lost_messages:
            self._note(f"{self._lost_messages} message(s) of channels declared only in a skipped chunk "
                       "(no intact summary to find them in)")
        self.health = FileHealth(bool(complete), self.file_bytes, read_to, problem, tuple(self._damage),
                                 self._skipped, self._expected())
        if complete:
            self._require_episode()  # a finished MCAP file without the actor's metadata is not an episode
        if not self.health.complete or self.health.damaged:
            log.debug("%s: %s", self.path, self.health.describe())

    def _check_data_crc(self, data_end: bytes) -> None:
        """The DataEnd record's CRC over the whole data section, when the writer kept one (0: it did not):
        the one check that sees a changed byte outside the chunks' CRCs, in a metadata value say."""
        if len(data_end) != 4:
            self._note(f"the DataEnd record is damaged (its length reads {len(data_end)}, not 4)")
            return
        stored = int.from_bytes(data_end, "little")
        if stored and not self._damage and stored != self._data_crc:
            self._note("the data section's CRC does not match: a byte outside the chunks changed (a metadata "
                       "record, a message index)")

    def _note(self, what: str) -> None:
        self._damage.append(what)

    def _expected(self) -> dict[str, int]:
        if self._summary is None:
            return {}
        out: dict[str, int] = {}
        for channel_id, count in self._summary.message_counts.items():
            channel = self._summary.channels.get(channel_id)
            if channel is not None:
                out[channel.topic] = out.get(channel.topic, 0) + count
        return out

    def _read_summary(self, f: io.BufferedReader) -> bool | None:
        """Check the footer and summary of a finished file: True when intact, False when damaged (named
        in the damage), None when the file has no footer (unfinished or cut: the walk says where it ends)."""
        if self.file_bytes < len(MCAP_MAGIC) + _FOOTER_TAIL:
            return None
        footer_at = self.file_bytes - _FOOTER_TAIL
        f.seek(footer_at)
        tail = f.read(_FOOTER_TAIL)
        if tail[-len(MCAP_MAGIC):] != MCAP_MAGIC:
            return None
        opcode, length = _RECORD_HEADER.unpack_from(tail)
        summary_start, _, crc = struct.unpack_from("<QQI", tail, _RECORD_HEADER.size)
        if opcode != _OP_FOOTER or length != 20 or not (summary_start == 0
                                                        or len(MCAP_MAGIC) < summary_start <= footer_at):
            self._note(f"the footer at byte {footer_at} is damaged")
            return False
        if summary_start == 0:
            return True  # a file written without a summary
        f.seek(summary_start)
        data = f.read(footer_at - summary_start)
        # The summary CRC covers the summary and the footer up to the CRC itself (MCAP specification).
        if crc and zlib.crc32(tail[:_RECORD_HEADER.size + 16], zlib.crc32(data)) != crc:
            self._note(f"the summary (bytes {summary_start}-{footer_at}) is damaged: its CRC does not match")
            return False
        try:
            self._summary = parse_summary(data, summary_start)
        except Exception as err:  # its CRC matched, so the writer wrote it so: named, not trusted
            self._note(f"the summary (bytes {summary_start}-{footer_at}) does not parse ({type(err).__name__})")
            return False
        return True

    def _records(self, f: io.BufferedReader) -> Iterator[tuple[int, bytes, int, int]]:
        """(opcode, body, start, end) of each whole record of the data section; where a record header is
        damaged, reading resumes at the next whole record (named in the damage); _Stop where the file
        ends inside a record and nothing whole follows."""
        offset = len(MCAP_MAGIC)
        while offset < self.file_bytes:
            f.seek(offset)
            header = f.read(_RECORD_HEADER.size)
            if len(header) < _RECORD_HEADER.size:
                raise _Stop(f"the file ends inside a record header at byte {offset}")
            opcode, length = _RECORD_HEADER.unpack(header)
            if offset == len(MCAP_MAGIC) and opcode != _OP_HEADER:
                raise NotMcapError(self.path, "not an MCAP file (the MCAP magic bytes are not followed by a "
                                   "Header record)")
            end = offset + _RECORD_HEADER.size + length
            if self._framed(f, opcode, length, end):
                f.seek(offset + _RECORD_HEADER.size)
                body = f.read(length)
                if len(body) != length:
                    raise _Stop(f"short read inside the record at byte {offset}")
                if opcode == _OP_HEADER:
                    self._good_until = end
                if opcode != _OP_DATA_END:
                    self._data_crc = zlib.crc32(body, zlib.crc32(header, self._data_crc))
                yield opcode, body, offset, end
                offset = end
                continue
            resume = self._resume_point(f)
            if resume is None:
                raise _Stop(self._torn(offset, opcode, end))
            self._note(f"no whole record starts at byte {offset} (a damaged record header): read on at the next "
                       f"whole record, byte {resume}")
            self._skipped += max(0, resume - offset)
            offset = resume

    def _framed(self, f: io.BufferedReader, opcode: int, length: int, end: int) -> bool:
        """A record header that can be believed: a known opcode, within the file, a chunk's lengths adding up."""
        if opcode not in _KNOWN_OPCODES or end > self.file_bytes:
            return False
        return opcode != _OP_CHUNK or chunk_fits(f.read(min(length, 64)), length)

    def _torn(self, offset: int, opcode: int, end: int) -> str:
        if opcode in _KNOWN_OPCODES and end > self.file_bytes:
            return (f"the file ends inside a {_op_name(opcode)} record that starts at byte {offset} "
                    f"({self.file_bytes - offset} of {end - offset} bytes present)")
        return f"no whole record from byte {offset} to the end ({self.file_bytes - offset} bytes)"

    def _resume_point(self, f: io.BufferedReader) -> int | None:
        """The start of the next whole record after the last one known whole: from the summary's indexes
        when there is one, else by scanning; None when none follows."""
        if self._summary is not None:
            for at in self._summary.resume_at:
                if at >= self._good_until and self._whole_record_at(f, at):
                    return at
        pos = self._good_until
        while pos < self.file_bytes:
            f.seek(pos)
            block = f.read(_SCAN_BLOCK)
            if not block:
                break
            for match in _CANDIDATE.finditer(block):
                if self._whole_record_at(f, pos + match.start()):
                    return pos + match.start()
            pos += len(block)
        return None

    def _whole_record_at(self, f: io.BufferedReader, at: int) -> bool:
        """True if a Chunk with lengths adding up and a matching CRC, a Metadata record that parses
        exactly, or the summary's DataEnd starts at byte `at`."""
        f.seek(at)
        header = f.read(_RECORD_HEADER.size)
        if len(header) < _RECORD_HEADER.size:
            return False
        opcode, length = _RECORD_HEADER.unpack(header)
        if at + _RECORD_HEADER.size + length > self.file_bytes:
            return False
        if opcode == _OP_DATA_END:
            return length == 4 and self._summary is not None and at == self._summary.data_end
        if opcode == _OP_CHUNK:
            if not chunk_fits(f.read(min(length, 64)), length):
                return False
            f.seek(at + _RECORD_HEADER.size)
            return isinstance(_chunk_records(f.read(length)), list)
        if opcode == _OP_METADATA and length <= _MAX_SCANNED_METADATA:
            return parse_metadata(f.read(length)) is not None
        return False

    def _handle(self, opcode: int, body: bytes, start: int, end: int,
                wanted: set[str] | None) -> Iterator[RecordedMessage]:
        if opcode in (_OP_CHUNK, _OP_MESSAGE, _OP_CHANNEL):
            self._require_episode()
        if opcode == _OP_CHUNK:
            records = _chunk_records(body)
            if isinstance(records, str):
                self._note(f"chunk at bytes {start}-{end} skipped: {records}")
                self._skipped += end - start
                return
            self._good_until = end
            for record in records:
                if isinstance(record, Message):
                    yield from self._message(record, end, wanted)
                elif isinstance(record, Schema):
                    self._schema(record)
                elif isinstance(record, Channel):
                    self._channel(record)
        elif opcode == _OP_METADATA:
            meta = parse_metadata(body)
            if meta is None:
                name = self._summary.metadata_names.get(start) if self._summary else None
                shown = f"the {name!r} metadata record" if name else "a metadata record"
                self._note(f"{shown} at byte {start} does not parse: skipped")
                return
            self._good_until = end
            self.metadata[meta.name] = dict(meta.metadata)
        elif opcode in (_OP_MESSAGE, _OP_SCHEMA, _OP_CHANNEL, _OP_ATTACHMENT):
            try:
                yield from self._loose(opcode, body, end, wanted)
            except EpisodeFileError:
                raise
            except Exception as err:  # struct.error, UnicodeDecodeError, EndOfFile: damaged bytes
                self._note(f"the {_op_name(opcode)} record at byte {start} does not parse ({type(err).__name__}): "
                           "skipped")
        # Header, message indexes and anything unknown carry nothing an episode reader needs.

    def _loose(self, opcode: int, body: bytes, end: int, wanted: set[str] | None) -> Iterator[RecordedMessage]:
        """A record outside any chunk (the actor chunks everything, other writers may not)."""
        stream = ReadDataStream(io.BytesIO(body))
        if opcode == _OP_MESSAGE:
            yield from self._message(Message.read(stream, len(body)), end, wanted)
        elif opcode == _OP_SCHEMA:
            self._schema(Schema.read(stream))
        elif opcode == _OP_CHANNEL:
            self._channel(Channel.read(stream))
        else:
            att = Attachment.read(stream)
            self.attachments.append((att.name, att.media_type, bytes(att.data)))

    def _require_episode(self) -> None:
        """The actor writes its metadata record before any channel or message. Where damage came first,
        that record may be what was damaged: the file is read, its damage already named."""
        if EPISODE_METADATA not in self.metadata and not self._damage:
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

    def _summary_channel(self, channel_id: int) -> ChannelInfo | None:
        """A channel declared in a skipped chunk, from its copy in the summary."""
        channel = self._summary.channels.get(channel_id) if self._summary else None
        if channel is None:
            return None
        schema = self._summary.schemas.get(channel.schema_id) if self._summary else None
        if schema is not None and channel.schema_id not in self._schemas:
            self._schema(schema)
        self._channel(channel)
        return self.channels.get(channel_id)

    def _message(self, message: Message, end: int, wanted: set[str] | None) -> Iterator[RecordedMessage]:
        channel = self.channels.get(message.channel_id) or self._summary_channel(message.channel_id)
        if channel is None:
            self._lost_messages += 1
            return
        if wanted is None or channel.topic in wanted:
            yield RecordedMessage(channel.topic, message.log_time, message.publish_time, message.sequence,
                                  bytes(message.data), end)


def _chunk_records(body: bytes) -> list | str | None:
    """The records of a Chunk record body with its CRC checked; a str saying why when it is damaged."""
    try:
        return breakup_chunk(Chunk.read(ReadDataStream(io.BytesIO(body))), validate_crc=True)
    except CRCValidationError:
        return "its CRC does not match"
    except Exception as err:  # bad compression, a record that does not parse: the chunk is damaged
        return f"it does not decompress or parse ({type(err).__name__})"


def _op_name(opcode: int) -> str:
    names = {_OP_HEADER: "Header", _OP_CHUNK: "Chunk", _OP_MESSAGE: "Message", _OP_METADATA: "Metadata",
             _OP_ATTACHMENT: "Attachment", _OP_SCHEMA: "Schema", _OP_CHANNEL: "Channel", 0x07: "MessageIndex",
             _OP_DATA_END: "DataEnd"}
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
