"""Recovery scan of one log segment (format in log.py): whole chunks only, CRC-checked, offsets exact.

The scan reads a segment with mmap, checks each chunk's CRC and each message's sequence (= item id mod
2^32), hands every message's bytes to a `parse` callback (which may reject it by raising ValueError),
and stops at the first torn or corrupt record. Everything from there to the end of the file is the
dropped tail: a chunk torn by a crash was never acknowledged (acks follow the chunk's fsync), so in that
case nothing acknowledged is lost. `repair_tail` then cuts the file at the last whole chunk (keeping the
dropped bytes beside it, for forensics) and appends DataEnd + Footer so it is a complete MCAP file.
"""

from __future__ import annotations

import mmap
import os
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from romannet.common.fsutil import fsync_directory

from .log import (
    CHUNK_FIXED_BYTES,
    MAGIC,
    MESSAGE_FIXED_BYTES,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_HEADER,
    OP_MESSAGE,
    SEGMENT_TRAILER,
    Location,
    segment_number,
)


class _Bad(Exception):
    """The record at the current offset is torn or corrupt."""


@dataclass
class ScanResult:
    """What a scan found in one segment file."""

    path: Path
    first_item_id: int | None = None  # from the channel metadata; None if the preamble is unreadable
    items: list[tuple[int, Location, Any]] = field(default_factory=list)  # (id, where, parse(data))
    good_end: int = 0  # offset just after the last whole record before the trailer
    file_size: int = 0
    finished: bool = False  # DataEnd + Footer + magic present
    problem: str | None = None  # why the scan stopped early
    dropped_records: int = 0  # transition records seen (at least partly) in the dropped tail

    @property
    def dropped_bytes(self) -> int:
        return 0 if self.finished else self.file_size - self.good_end


def _header(buf: Any, pos: int, end: int) -> tuple[int, int, int]:
    """(opcode, body length, body start) of the record at pos, or _Bad if it does not fit the file."""
    if pos + 9 > end:
        raise _Bad(f"record header cut off at offset {pos} ({end - pos} of 9 bytes)")
    opcode, length = struct.unpack_from("<BQ", buf, pos)
    if pos + 9 + length > end:
        raise _Bad(f"record (opcode 0x{opcode:02x}) at offset {pos} needs {9 + length} bytes; "
                   f"only {end - pos} remain")
    return opcode, length, pos + 9


def _channel_first_id(buf: Any, body: int, length: int) -> int:
    pos = body + 4  # channel id, schema id
    for _ in range(2):  # topic, message encoding
        (n,) = struct.unpack_from("<I", buf, pos)
        pos += 4 + n
    (map_len,) = struct.unpack_from("<I", buf, pos)
    pos += 4
    stop = pos + map_len
    while pos < stop:
        (kn,) = struct.unpack_from("<I", buf, pos)
        key = bytes(buf[pos + 4:pos + 4 + kn]).decode()
        pos += 4 + kn
        (vn,) = struct.unpack_from("<I", buf, pos)
        value = bytes(buf[pos + 4:pos + 4 + vn]).decode()
        pos += 4 + vn
        if key == "first_item_id":
            return int(value)
    raise _Bad("channel metadata has no first_item_id")


def _count_messages(buf: Any, pos: int, end: int) -> int:
    """Best-effort count of message records in a torn or corrupt chunk (for the warning)."""
    count = 0
    while pos + 9 <= end:
        opcode, length = struct.unpack_from("<BQ", buf, pos)
        if opcode != OP_MESSAGE or length > end:
            break
        count += 1
        pos += 9 + length
    return count


def scan_segment(path: Path, parse: Callable[[memoryview], Any], start_offset: int | None = None,
                 start_item_id: int | None = None) -> ScanResult:
    """Scan `path` from its first chunk, or from a chunk at start_offset whose first item is start_item_id."""
    result = ScanResult(path)
    size = path.stat().st_size
    result.file_size = size
    if size == 0:
        result.problem = "empty file (crash while the segment was being created)"
        return result
    with path.open("rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        buf = memoryview(mm)
        try:
            _scan(buf, size, path, parse, start_offset, start_item_id, result)
        finally:
            buf.release()
    return result


def _scan(buf: memoryview, size: int, path: Path, parse: Callable[[memoryview], Any], start_offset: int | None,
          start_item_id: int | None, result: ScanResult) -> None:
    segment = segment_number(path)
    pos = 0
    next_id: int | None = None
    try:
        if bytes(buf[:8]) != MAGIC:
            raise _Bad("no MCAP magic at the start")
        pos = 8
        while next_id is None:  # preamble: Header, Schema, Channel
            opcode, length, body = _header(buf, pos, size)
            if opcode == OP_CHANNEL:
                result.first_item_id = next_id = _channel_first_id(buf, body, length)
            elif opcode not in (OP_HEADER, 0x03):
                raise _Bad(f"unexpected record 0x{opcode:02x} before the channel at offset {pos}")
            pos = body + length
        result.good_end = pos
        if start_offset is not None:
            pos, next_id = start_offset, start_item_id
            result.good_end = pos
        while pos < size:
            opcode, length, body = _header(buf, pos, size)
            if opcode == OP_DATA_END:
                trailer_end = pos + len(SEGMENT_TRAILER)
                if bytes(buf[pos:trailer_end]) == SEGMENT_TRAILER and trailer_end == size:
                    result.finished = True
                    return
                if buf[pos + 9 + length:pos + 10 + length].tobytes() == bytes([OP_FOOTER]) and \
                        bytes(buf[size - 8:size]) == MAGIC:
                    result.finished = True  # another writer's trailer (e.g. with a summary)
                    return
                raise _Bad(f"incomplete file trailer at offset {pos}")
            if opcode != OP_CHUNK:
                pos = body + length  # MCAP readers skip records they do not need; so do we
                result.good_end = pos
                continue
            next_id = _scan_chunk(buf, pos, body, length, segment, next_id, parse, result)  # type: ignore[arg-type]
            pos = body + length
            result.good_end = pos
    except _Bad as bad:
        result.problem = str(bad)
        if pos + CHUNK_FIXED_BYTES <= size and buf[pos] == OP_CHUNK:
            result.dropped_records = _count_messages(buf, pos + CHUNK_FIXED_BYTES, size)
    except (struct.error, ValueError, UnicodeDecodeError) as exc:
        result.problem = f"unreadable record at offset {pos}: {exc}"


def _scan_chunk(buf: memoryview, pos: int, body: int, length: int, segment: int, next_id: int,
                parse: Callable[[memoryview], Any], result: ScanResult) -> int:
    """Check one chunk and add its items to result (all or none). Returns the next item id."""
    _, _, _, crc, comp_len = struct.unpack_from("<QQQII", buf, body)
    if comp_len != 0:
        raise _Bad(f"chunk at offset {pos} is compressed; this log writes uncompressed chunks")
    (records_len,) = struct.unpack_from("<Q", buf, body + 32)
    start = pos + CHUNK_FIXED_BYTES
    end = body + length
    if start + records_len != end:
        raise _Bad(f"chunk at offset {pos} has inconsistent lengths")
    if crc != 0 and zlib.crc32(buf[start:end]) != crc:
        raise _Bad(f"chunk at offset {pos} fails its CRC check (corrupt data)")
    items = []
    rpos = start
    while rpos < end:
        opcode, rlen, rbody = _header(buf, rpos, end)
        if opcode == OP_MESSAGE:
            if rlen < MESSAGE_FIXED_BYTES - 9:
                raise _Bad(f"message record at offset {rpos} too short")
            _, sequence = struct.unpack_from("<HI", buf, rbody)
            if sequence != next_id & 0xFFFFFFFF:
                raise _Bad(f"message at offset {rpos} has sequence {sequence}; expected item {next_id}")
            data_offset = rbody + MESSAGE_FIXED_BYTES - 9
            data = buf[data_offset:rbody + rlen]
            try:
                meta = parse(data)
            except ValueError as exc:
                raise _Bad(f"item {next_id} at offset {rpos}: {exc}") from exc
            items.append((next_id, Location(segment, pos, items[0][0] if items else next_id, data_offset,
                                            len(data)), meta))
            next_id += 1
        rpos = rbody + rlen
    result.items.extend(items)
    return next_id


def repair_tail(result: ScanResult) -> None:
    """Cut a segment after its last whole chunk, keep the cut bytes in `<name>.tail-<offset>.bad`, and
    append DataEnd + Footer so the file is a complete MCAP. A file without a readable preamble is
    renamed to `<name>.bad` (it holds no acknowledged item: the preamble is fsync'ed before any chunk)."""
    path = result.path
    if result.finished:
        return
    if result.first_item_id is None:
        path.rename(path.with_name(path.name + ".bad"))
        fsync_directory(path.parent)
        return
    if result.dropped_bytes:
        with path.open("rb") as fh:
            fh.seek(result.good_end)
            tail = fh.read()
        keep = path.with_name(f"{path.name}.tail-{result.good_end}.bad")
        keep.write_bytes(tail)
    with path.open("r+b") as fh:
        fh.truncate(result.good_end)
        fh.seek(result.good_end)
        fh.write(SEGMENT_TRAILER)
        fh.flush()
        os.fsync(fh.fileno())
    fsync_directory(path.parent)
