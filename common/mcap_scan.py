"""The damage-tolerant walk over an MCAP file's records, apart from what the records mean: where each whole
record is, which chunks and records are damaged, where reading can resume after a broken record header, and
what an intact summary section offers for that. common.episode_file's EpisodeReader reads episodes through
it; the rules for what damage costs are described there (and in docs/recording.md).

Kept apart so the byte-level framing rules of MCAP (record headers, chunk lengths, CRCs, the footer and
summary) live in one place, free of what an episode is.
"""

from __future__ import annotations

import io
import re
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field

from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Chunk, ChunkIndex, Metadata, MetadataIndex, Schema, Statistics
from mcap.stream_reader import CRCValidationError, breakup_chunk

MCAP_MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_CHUNK_INDEX, OP_ATTACHMENT, OP_STATISTICS, OP_METADATA, OP_METADATA_INDEX, OP_DATA_END = (
    0x08, 0x09, 0x0B, 0x0C, 0x0D, 0x0F)
_RECORD_HEADER = struct.Struct("<BQ")


class ScanStop(Exception):
    """Reading ends here: the file is torn at this point and nothing whole follows (not an error of the caller)."""


@dataclass
class Summary:
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


def parse_summary(data: bytes, summary_start: int) -> Summary:
    """The records of a summary section (the bytes from its start to the Footer) in a Summary."""
    out = Summary(data_end=summary_start - _RECORD_HEADER.size - 4)
    offset = 0
    while offset + _RECORD_HEADER.size <= len(data):
        opcode, length = _RECORD_HEADER.unpack_from(data, offset)
        body = data[offset + _RECORD_HEADER.size:offset + _RECORD_HEADER.size + length]
        offset += _RECORD_HEADER.size + length
        stream = ReadDataStream(io.BytesIO(body))
        if opcode == OP_SCHEMA:
            schema = Schema.read(stream)
            out.schemas[schema.id] = schema
        elif opcode == OP_CHANNEL:
            channel = Channel.read(stream)
            out.channels[channel.id] = channel
        elif opcode == OP_CHUNK_INDEX:
            out.resume_at.append(ChunkIndex.read(stream).chunk_start_offset)
        elif opcode == OP_METADATA_INDEX:
            index = MetadataIndex.read(stream)
            out.resume_at.append(index.offset)
            out.metadata_names[index.offset] = index.name
        elif opcode == OP_STATISTICS:
            out.message_counts = dict(Statistics.read(stream).channel_message_counts)
    out.resume_at = sorted({*out.resume_at, out.data_end})
    return out


class NotMcapData(Exception):
    """The bytes after the MCAP magic are not MCAP records (the reader names the file)."""


class DataScan:
    """One front-to-back walk over the data section of a file of `file_bytes` bytes: whole records in
    order, the damage met on the way (`damage`, `skipped` bytes) and the summary when it is intact."""

    def __init__(self, file_bytes: int):
        self.file_bytes = file_bytes
        self.summary: Summary | None = None
        self.damage: list[str] = []
        self.skipped = 0
        self.good_until = len(MCAP_MAGIC)  # end of the last record known whole (CRC, exact parse)
        self.data_crc = zlib.crc32(MCAP_MAGIC)  # over the records read so far, for the DataEnd record's CRC

    def check_data_crc(self, data_end: bytes) -> None:
        """The DataEnd record's CRC over the whole data section, when the writer kept one (0: it did not):
        the one check that sees a changed byte outside the chunks' CRCs, in a metadata value say."""
        if len(data_end) != 4:
            self.note(f"the DataEnd record is damaged (its length reads {len(data_end)}, not 4)")
            return
        stored = int.from_bytes(data_end, "little")
        if stored and not self.damage and stored != self.data_crc:
            self.note("the data section's CRC does not match: a byte outside the chunks changed (a metadata "
                      "record, a message index)")

    def note(self, what: str) -> None:
        self.damage.append(what)

    def read_summary(self, f: io.BufferedReader) -> bool | None:
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
        if opcode != OP_FOOTER or length != 20 or not (summary_start == 0
                                                        or len(MCAP_MAGIC) < summary_start <= footer_at):
            self.note(f"the footer at byte {footer_at} is damaged")
            return False
        if summary_start == 0:
            return True  # a file written without a summary
        f.seek(summary_start)
        data = f.read(footer_at - summary_start)
        # The summary CRC covers the summary and the footer up to the CRC itself (MCAP specification).
        if crc and zlib.crc32(tail[:_RECORD_HEADER.size + 16], zlib.crc32(data)) != crc:
            self.note(f"the summary (bytes {summary_start}-{footer_at}) is damaged: its CRC does not match")
            return False
        try:
            self.summary = parse_summary(data, summary_start)
        except Exception as err:  # its CRC matched, so the writer wrote it so: named, not trusted
            self.note(f"the summary (bytes {summary_start}-{footer_at}) does not parse ({type(err).__name__})")
            return False
        return True

    def records(self, f: io.BufferedReader) -> Iterator[tuple[int, bytes, int, int]]:
        """(opcode, body, start, end) of each whole record of the data section; where a record header is
        damaged, reading resumes at the next whole record (named in the damage); ScanStop where the file
        ends inside a record and nothing whole follows."""
        offset = len(MCAP_MAGIC)
        while offset < self.file_bytes:
            f.seek(offset)
            header = f.read(_RECORD_HEADER.size)
            if len(header) < _RECORD_HEADER.size:
                raise ScanStop(f"the file ends inside a record header at byte {offset}")
            opcode, length = _RECORD_HEADER.unpack(header)
            if offset == len(MCAP_MAGIC) and opcode != OP_HEADER:
                raise NotMcapData("not an MCAP file (the MCAP magic bytes are not followed by a Header record)")
            end = offset + _RECORD_HEADER.size + length
            if self._framed(f, opcode, length, end):
                f.seek(offset + _RECORD_HEADER.size)
                body = f.read(length)
                if len(body) != length:
                    raise ScanStop(f"short read inside the record at byte {offset}")
                if opcode == OP_HEADER:
                    self.good_until = end
                if opcode != OP_DATA_END:
                    self.data_crc = zlib.crc32(body, zlib.crc32(header, self.data_crc))
                yield opcode, body, offset, end
                offset = end
                continue
            resume = self._resume_point(f)
            if resume is None:
                raise ScanStop(self._torn(offset, opcode, end))
            self.note(f"no whole record starts at byte {offset} (a damaged record header): read on at the next "
                      f"whole record, byte {resume}")
            self.skipped += max(0, resume - offset)
            offset = resume

    def _framed(self, f: io.BufferedReader, opcode: int, length: int, end: int) -> bool:
        """A record header that can be believed: a known opcode, within the file, a chunk's lengths adding up."""
        if opcode not in _KNOWN_OPCODES or end > self.file_bytes:
            return False
        return opcode != OP_CHUNK or chunk_fits(f.read(min(length, 64)), length)

    def _torn(self, offset: int, opcode: int, end: int) -> str:
        if opcode in _KNOWN_OPCODES and end > self.file_bytes:
            return (f"the file ends inside a {op_name(opcode)} record that starts at byte {offset} "
                    f"({self.file_bytes - offset} of {end - offset} bytes present)")
        return f"no whole record from byte {offset} to the end ({self.file_bytes - offset} bytes)"

    def _resume_point(self, f: io.BufferedReader) -> int | None:
        """The start of the next whole record after the last one known whole: from the summary's indexes
        when there is one, else by scanning; None when none follows."""
        if self.summary is not None:
            for at in self.summary.resume_at:
                if at >= self.good_until and self._whole_record_at(f, at):
                    return at
        pos = self.good_until
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
        if opcode == OP_DATA_END:
            return length == 4 and self.summary is not None and at == self.summary.data_end
        if opcode == OP_CHUNK:
            if not chunk_fits(f.read(min(length, 64)), length):
                return False
            f.seek(at + _RECORD_HEADER.size)
            return isinstance(chunk_records(f.read(length)), list)
        if opcode == OP_METADATA and length <= _MAX_SCANNED_METADATA:
            return parse_metadata(f.read(length)) is not None
        return False


def chunk_records(body: bytes) -> list | str | None:
    """The records of a Chunk record body with its CRC checked; a str saying why when it is damaged."""
    try:
        return breakup_chunk(Chunk.read(ReadDataStream(io.BytesIO(body))), validate_crc=True)
    except CRCValidationError:
        return "its CRC does not match"
    except Exception as err:  # bad compression, a record that does not parse: the chunk is damaged
        return f"it does not decompress or parse ({type(err).__name__})"


def op_name(opcode: int) -> str:
    names = {OP_HEADER: "Header", OP_CHUNK: "Chunk", OP_MESSAGE: "Message", OP_METADATA: "Metadata",
             OP_ATTACHMENT: "Attachment", OP_SCHEMA: "Schema", OP_CHANNEL: "Channel", 0x07: "MessageIndex",
             OP_DATA_END: "DataEnd"}
    return names.get(opcode, f"opcode-0x{opcode:02x}")
