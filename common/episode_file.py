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
  parses is seen only through the CRC over the whole data section (the actor and `mcap rescore` keep it;
  other writers may leave it out, 0);
- messages of channels whose declaration was in a skipped chunk are read through the copies of every
  channel in the summary; without a summary they cannot be read and are counted;
- a summary whose CRC does not match, or a damaged footer, is named; the data is read all the same.

Nothing here unpickles: messages stay bytes (protobuf / JSON), decoded by the caller with the validating
decoders of common.wire.

A file that is not an episode raises one EpisodeFileError subclass whose message starts with the path:
NotMcapError (no MCAP magic, empty, unreadable) or ForeignMcapError (a channel with a schema episode
files never use, /transition with another schema, or no "romannet" metadata record before the first
chunk: the actor writes that record before any message). The format is documented in docs/recording.md.
The byte-level walk (record framing, CRCs, resuming after damage, the summary) is common.mcap_scan's; this
module gives the records their meaning as an episode.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.records import Attachment, Channel, Message, Schema

from .errors import RomannetError
from .mcap_scan import (
    MCAP_MAGIC,
    OP_ATTACHMENT,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_MESSAGE,
    OP_METADATA,
    OP_SCHEMA,
    DataScan,
    NotMcapData,
    ScanStop,
    chunk_records,
    op_name,
    parse_metadata,
)

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
                           ("foxglove.FrameTransforms", "protobuf"), ("foxglove.CameraCalibration", "protobuf"),
                           (TRANSITION_SCHEMA, "protobuf"), (STEP_SCHEMA, "jsonschema")})
EPISODE_METADATA = "romannet"  # run id, actor id, episode id, task, seed, weights version, units
CONFIG_METADATA = "config"  # {"toml": the resolved config}
END_METADATA = "episode_end"  # done reason, steps, efficiency, weights version at the end

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



class EpisodeReader:
    """One episode file, read front to back; see the module docstring."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: list[tuple[str, str, bytes]] = []  # (name, media type, data)
        self.channels: dict[int, ChannelInfo] = {}
        self.health: FileHealth | None = None  # set when messages() has run to its end
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        self._lost_messages = 0  # of channels declared only in a skipped chunk
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
        self._scan = DataScan(self.file_bytes)  # the walk of the last messages() call: damage, summary

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
        scan = self._scan = DataScan(self.file_bytes)
        self._lost_messages = 0
        try:
            with open(self.path, "rb") as f:
                footer_ok = scan.read_summary(f)
                for opcode, body, start, end in scan.records(f):
                    if opcode == OP_DATA_END:
                        scan.check_data_crc(body)
                        read_to = end
                        complete = footer_ok is not None  # a damaged summary is named in the damage
                        if footer_ok is None:
                            problem = "the summary or footer after the data is missing (cut or zeroed)"
                        break
                    yield from self._handle(opcode, body, start, end, wanted)
                    read_to = end
                else:
                    problem = "the file ends without a summary or footer (the writer did not finish it)"
        except ScanStop as stop:
            problem = str(stop)
        except NotMcapData as err:
            raise NotMcapError(self.path, str(err)) from None
        except OSError as err:  # a failing disk: what was read stands, the rest is named
            problem = f"reading failed after byte {read_to} ({err.strerror or err})"
        if self._lost_messages:
            scan.note(f"{self._lost_messages} message(s) of channels declared only in a skipped chunk "
                      "(no intact summary to find them in)")
        self.health = FileHealth(bool(complete), self.file_bytes, read_to, problem, tuple(scan.damage),
                                 scan.skipped, self._expected())
        if complete:
            self._require_episode()  # a finished MCAP file without the actor's metadata is not an episode
        if not self.health.complete or self.health.damaged:
            log.debug("%s: %s", self.path, self.health.describe())


    def _expected(self) -> dict[str, int]:
        if self._scan.summary is None:
            return {}
        out: dict[str, int] = {}
        for channel_id, count in self._scan.summary.message_counts.items():
            channel = self._scan.summary.channels.get(channel_id)
            if channel is not None:
                out[channel.topic] = out.get(channel.topic, 0) + count
        return out


    def _handle(self, opcode: int, body: bytes, start: int, end: int,
                wanted: set[str] | None) -> Iterator[RecordedMessage]:
        if opcode in (OP_CHUNK, OP_MESSAGE, OP_CHANNEL):
            self._require_episode()
        if opcode == OP_CHUNK:
            records = chunk_records(body)
            if isinstance(records, str):
                self._scan.note(f"chunk at bytes {start}-{end} skipped: {records}")
                self._scan.skipped += end - start
                return
            self._scan.good_until = end
            for record in records:
                if isinstance(record, Message):
                    yield from self._message(record, end, wanted)
                elif isinstance(record, Schema):
                    self._schema(record)
                elif isinstance(record, Channel):
                    self._channel(record)
        elif opcode == OP_METADATA:
            meta = parse_metadata(body)
            if meta is None:
                name = self._scan.summary.metadata_names.get(start) if self._scan.summary else None
                shown = f"the {name!r} metadata record" if name else "a metadata record"
                self._scan.note(f"{shown} at byte {start} does not parse: skipped")
                return
            self._scan.good_until = end
            self.metadata[meta.name] = dict(meta.metadata)
        elif opcode in (OP_MESSAGE, OP_SCHEMA, OP_CHANNEL, OP_ATTACHMENT):
            try:
                yield from self._loose(opcode, body, end, wanted)
            except EpisodeFileError:
                raise
            except Exception as err:  # struct.error, UnicodeDecodeError, EndOfFile: damaged bytes
                self._scan.note(f"the {op_name(opcode)} record at byte {start} does not parse "
                                f"({type(err).__name__}): skipped")
        # Header, message indexes and anything unknown carry nothing an episode reader needs.

    def _loose(self, opcode: int, body: bytes, end: int, wanted: set[str] | None) -> Iterator[RecordedMessage]:
        """A record outside any chunk (the actor chunks everything, other writers may not)."""
        stream = ReadDataStream(io.BytesIO(body))
        if opcode == OP_MESSAGE:
            yield from self._message(Message.read(stream, len(body)), end, wanted)
        elif opcode == OP_SCHEMA:
            self._schema(Schema.read(stream))
        elif opcode == OP_CHANNEL:
            self._channel(Channel.read(stream))
        else:
            att = Attachment.read(stream)
            self.attachments.append((att.name, att.media_type, bytes(att.data)))

    def _require_episode(self) -> None:
        """The actor writes its metadata record before any channel or message. Where damage came first,
        that record may be what was damaged: the file is read, its damage already named."""
        if EPISODE_METADATA not in self.metadata and not self._scan.damage:
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
        channel = self._scan.summary.channels.get(channel_id) if self._scan.summary else None
        if channel is None:
            return None
        schema = self._scan.summary.schemas.get(channel.schema_id) if self._scan.summary else None
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
