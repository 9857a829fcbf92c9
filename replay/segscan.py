"""Recovery scan of one log segment (format in log.py): every record that checks out, offsets exact.

The scan walks a segment's records with mmap. A chunk whose CRC holds is taken whole; a chunk that fails
it is entered, and each of its messages is kept when its own checksum (recordcheck.py) holds. Any record
that does not check out starts a resynchronisation: the scan looks for the next message record whose
framing, item id and checksum are all right, and goes on from there. So damage costs only the records
it touches, and the stretch skipped is reported as a Damage (which item ids it held is for recovery.py
to say, from the ids on either side).

A chunk cut off by the end of the file (its header whole and consistent, its body short) is a write torn
by a crash: never acknowledged, since acks follow the chunk's fsync. `repair_tail` cuts such a tail
(keeping the bytes beside the file, for forensics) and appends DataEnd + Footer so the segment is a
complete MCAP file; damaged bytes elsewhere stay where they are. Segments written before records had
checksums (legacy) keep the old rule: a chunk that fails its CRC is lost whole.
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
    OP_HEADER,
    OP_MESSAGE,
    OP_SCHEMA,
    SEGMENT_TRAILER,
    Location,
    is_legacy_segment,
    segment_number,
)
from .recordcheck import record_problem

# Bytes 5..10 of a message record: the high half of its 8-byte length (records are < 4 GiB) and channel 1.
_MESSAGE_SIGNATURE = b"\x00\x00\x00\x00\x01\x00"
_ID_WINDOW = 1 << 24  # how far past the expected id a resynchronised record's id may lie


class _Bad(Exception):
    """The record at the current offset is damaged."""


class _Torn(Exception):
    """The file ends inside a record whose header is whole: a write cut short by a crash."""


@dataclass
class Damage:
    """A stretch [offset, end) of a segment in which no record checked out."""

    offset: int
    end: int
    reason: str
    named_ids: list[int] = field(default_factory=list)  # ids read from damaged message headers (best effort)


@dataclass
class ScanResult:
    """What a scan found in one segment file."""

    path: Path
    first_item_id: int | None = None  # from the channel metadata; None if the preamble is unreadable
    items: list[tuple[int, Location, Any]] = field(default_factory=list)  # (id, where, parse(data))
    good_end: int = 0  # where a torn tail starts (the file size when there is none)
    file_size: int = 0
    finished: bool = False  # DataEnd + Footer + magic present
    legacy: bool = False  # records without their own checksum
    damage: list[Damage] = field(default_factory=list)
    torn: bool = False  # the file ends in a chunk torn by a crash
    torn_records: int = 0  # message records seen (at least partly) in the torn chunk
    preamble_problem: str | None = None

    @property
    def dropped_bytes(self) -> int:
        """Bytes of a torn tail (cut by repair_tail)."""
        return self.file_size - self.good_end if self.torn else 0


def _header(buf: Any, pos: int, end: int) -> tuple[int, int, int]:
    """(opcode, body length, body start) of the record at pos; _Torn if the file ends inside it."""
    if pos + 9 > end:
        raise _Torn(f"record header cut off at offset {pos} ({end - pos} of 9 bytes)")
    opcode, length = struct.unpack_from("<BQ", buf, pos)
    if pos + 9 + length > end:
        raise _Torn(f"record (opcode 0x{opcode:02x}) at offset {pos} needs {9 + length} bytes; "
                    f"only {end - pos} remain")
    return opcode, length, pos + 9


def _channel_first_id(buf: Any, body: int, length: int) -> int:
    pos = body + 4  # channel id, schema id
    for _ in range(2):  # topic, message encoding
        (n,) = struct.unpack_from("<I", buf, pos)
        pos += 4 + n
    (map_len,) = struct.unpack_from("<I", buf, pos)
    pos += 4
    stop = min(pos + map_len, body + length)
    while pos < stop:
        (kn,) = struct.unpack_from("<I", buf, pos)
        key = bytes(buf[pos + 4:pos + 4 + kn]).decode()
        pos += 4 + kn
        (vn,) = struct.unpack_from("<I", buf, pos)
        value = bytes(buf[pos + 4:pos + 4 + vn]).decode()
        pos += 4 + vn
        if key == "first_item_id":
            return int(value)
    raise ValueError("channel metadata has no first_item_id")


def full_id(sequence: int, expected: int | None) -> int:
    """The item id whose low 32 bits are `sequence`: the first one at or after `expected`."""
    if expected is None:
        return sequence
    candidate = (expected & ~0xFFFFFFFF) | sequence
    return candidate if candidate >= expected else candidate + (1 << 32)


def _count_messages(buf: Any, pos: int, end: int) -> int:
    """Best-effort count of message records in a torn chunk (for the warning)."""
    count = 0
    while pos + 9 <= end:
        opcode, length = struct.unpack_from("<BQ", buf, pos)
        if opcode != OP_MESSAGE or length > end:
            break
        count += 1
        pos += 9 + length
    return count


class _Scanner:
    """One pass over one segment; fills a ScanResult."""

    def __init__(self, mm: mmap.mmap, path: Path, parse: Callable[[memoryview], Any], result: ScanResult):
        self.mm, self.buf, self.size = mm, memoryview(mm), len(mm)
        self.segment = segment_number(path)
        self.parse, self.result = parse, result
        self.next_id: int | None = None

    def close(self) -> None:
        self.buf.release()

    # ------------------------------------------------------------------------------------ preamble
    def preamble(self) -> int:
        """Offset after Header, Schema and Channel (sets first_item_id); 8 or 0 when unreadable."""
        buf, size = self.buf, self.size
        if bytes(buf[:8]) != MAGIC:
            self.result.preamble_problem = "no MCAP magic at the start"
            return 0
        pos = 8
        try:
            while True:
                opcode, length, body = _header(buf, pos, size)
                if opcode == OP_CHANNEL:
                    self.result.first_item_id = self.next_id = _channel_first_id(buf, body, length)
                    return body + length
                if opcode not in (OP_HEADER, OP_SCHEMA):
                    raise ValueError(f"unexpected record 0x{opcode:02x} before the channel at offset {pos}")
                pos = body + length
        except (_Torn, struct.error, ValueError, UnicodeDecodeError) as exc:
            self.result.preamble_problem = f"unreadable preamble: {exc}"
            return 8

    # ------------------------------------------------------------------------------------- records
    def walk(self, pos: int) -> None:
        result, size = self.result, self.size
        while pos < size:
            try:
                pos = self._step(pos)
            except _Torn as torn:
                if self._is_torn_chunk(pos) and self._resync(pos + 1) is None:  # a tail cut by a crash
                    result.torn, result.good_end = True, pos
                    result.torn_records = _count_messages(self.buf, pos + CHUNK_FIXED_BYTES, size)
                    return
                pos = self._skip_damage(pos, str(torn))
            except (_Bad, struct.error, ValueError, UnicodeDecodeError) as bad:
                pos = self._skip_damage(pos, str(bad))
            if pos < 0:
                return

    def _is_torn_chunk(self, pos: int) -> bool:
        """Whether pos starts a chunk whose header is whole and consistent, or is cut off itself."""
        rest = self.size - pos
        if self.buf[pos] != OP_CHUNK:
            return False
        if rest < CHUNK_FIXED_BYTES:
            return True
        _, length, _, _, records_len, _, comp_len, records_len2 = struct.unpack_from("<BQQQQIIQ", self.buf, pos)
        return comp_len == 0 and records_len == records_len2 and length == CHUNK_FIXED_BYTES - 9 + records_len

    def _skip_damage(self, pos: int, reason: str) -> int:
        """Record the damaged stretch from pos; the offset to go on from, or -1 at the end of the file."""
        found = self._resync(pos + 1)
        end = found if found is not None else self.size
        if found is None and self.size - pos >= len(SEGMENT_TRAILER) and \
                bytes(self.buf[self.size - len(SEGMENT_TRAILER):]) == SEGMENT_TRAILER:
            end = self.size - len(SEGMENT_TRAILER)
            self.result.finished = True
        self.result.damage.append(Damage(pos, end, reason, self._named_ids(pos, end)))
        return found if found is not None else -1

    def _step(self, pos: int) -> int:
        """Handle the record at pos; returns the offset of the next one."""
        opcode, length, body = _header(self.buf, pos, self.size)
        if opcode == OP_DATA_END:
            trailer_end = pos + len(SEGMENT_TRAILER)
            if bytes(self.buf[pos:trailer_end]) == SEGMENT_TRAILER and trailer_end == self.size:
                self.result.finished = True
                return self.size
            raise _Bad(f"misplaced or incomplete file trailer at offset {pos}")
        if opcode == OP_CHUNK:
            return self._chunk(pos, length, body)
        if opcode == OP_MESSAGE:
            self._take(self._message(pos, length, body, self.next_id))
            return body + length
        raise _Bad(f"unexpected record 0x{opcode:02x} at offset {pos}")

    def _chunk(self, pos: int, length: int, body: int) -> int:
        """A chunk whose CRC holds: all its items; otherwise step inside and check message by message."""
        _, _, records_len, crc, comp_len = struct.unpack_from("<QQQII", self.buf, body)
        (records_len2,) = struct.unpack_from("<Q", self.buf, body + 32)
        if comp_len != 0 or records_len != records_len2 or length != CHUNK_FIXED_BYTES - 9 + records_len:
            raise _Bad(f"chunk header at offset {pos} is inconsistent")
        start, end = pos + CHUNK_FIXED_BYTES, body + length
        if crc != 0 and zlib.crc32(self.buf[start:end]) != crc:
            if self.result.legacy:
                raise _Bad(f"chunk at offset {pos} fails its CRC check and its records have no checksums")
            return start  # the walk checks each message on its own
        items, next_id, rpos = [], self.next_id, start
        while rpos < end:
            opcode, rlen, rbody = _header(self.buf, rpos, end)
            if opcode != OP_MESSAGE:
                raise _Bad(f"record 0x{opcode:02x} at offset {rpos} inside a chunk")
            item = self._message(rpos, rlen, rbody, next_id, chunk=(pos, items[0][0] if items else None))
            items.append(item)
            next_id = item[0] + 1
            rpos = rbody + rlen
        for item in items:
            self._take(item)
        return end

    def _message(self, pos: int, length: int, body: int, expected: int | None,
                 chunk: tuple[int, int | None] | None = None) -> tuple[int, Location, Any]:
        """(id, location, parsed) of the message at pos, or _Bad. Inside a CRC-checked chunk the id must be
        the next one; elsewhere it may skip ahead (records were lost) and the record's checksum must hold."""
        if length < MESSAGE_FIXED_BYTES - 9:
            raise _Bad(f"message record at offset {pos} too short")
        _, sequence = struct.unpack_from("<HI", self.buf, body)
        item_id = full_id(sequence, expected)
        if chunk is not None and expected is not None and item_id != expected:
            raise _Bad(f"message at offset {pos} has sequence {sequence}; expected item {expected}")
        if expected is not None and item_id - expected > _ID_WINDOW:
            raise _Bad(f"message at offset {pos} has an implausible item id {item_id}")
        data_offset = body + MESSAGE_FIXED_BYTES - 9
        data = self.buf[data_offset:body + length]
        if chunk is None:
            if self.result.legacy:
                raise _Bad(f"message at offset {pos} outside a sound chunk, without a checksum")
            problem = record_problem(item_id, data)
            if problem:
                raise _Bad(f"{problem} (offset {pos})")
        try:
            meta = self.parse(data)  # the check field is one more (unknown) protobuf field
        except ValueError as exc:
            raise _Bad(f"item {item_id} at offset {pos}: {exc}") from exc
        chunk_offset, chunk_first = chunk if chunk is not None else (pos, item_id)
        return item_id, Location(self.segment, chunk_offset, item_id if chunk_first is None else chunk_first,
                                 data_offset, len(data)), meta

    def _take(self, item: tuple[int, Location, Any]) -> None:
        self.result.items.append(item)
        self.next_id = item[0] + 1

    def _resync(self, start: int) -> int | None:
        """Offset of the next message record at or after start that checks out completely, or None."""
        if self.result.legacy:
            return None
        probe = start + 5
        while True:
            hit = self.mm.find(_MESSAGE_SIGNATURE, probe)
            if hit < 0:
                return None
            pos = hit - 5
            probe = hit + 1
            if pos < start or self.buf[pos] != OP_MESSAGE:
                continue
            try:
                _, length, body = _header(self.buf, pos, self.size)
                self._message(pos, length, body, self.next_id)
            except (_Bad, _Torn, struct.error, ValueError):
                continue
            return pos

    def _named_ids(self, start: int, end: int) -> list[int]:
        """Ids in the sequence fields of message-like headers in [start, end) (for a damaged tail)."""
        ids: list[int] = []
        probe = start + 5
        while (hit := self.mm.find(_MESSAGE_SIGNATURE, probe, end + 5)) >= 0:
            probe = hit + 1
            pos = hit - 5
            if pos < start or self.buf[pos] != OP_MESSAGE or pos + 15 > self.size:
                continue
            (sequence,) = struct.unpack_from("<I", self.buf, pos + 11)
            item_id = full_id(sequence, self.next_id)
            if self.next_id is None or item_id - self.next_id <= _ID_WINDOW:
                ids.append(item_id)
        return sorted(set(ids))


def scan_segment(path: Path, parse: Callable[[memoryview], Any], start_offset: int | None = None,
                 start_item_id: int | None = None) -> ScanResult:
    """Scan `path` from its first record, or from the record at start_offset whose item is start_item_id."""
    result = ScanResult(path, legacy=is_legacy_segment(path))
    size = path.stat().st_size
    result.file_size = result.good_end = size
    if size < len(MAGIC):
        result.preamble_problem = "empty file" if size == 0 else f"only {size} byte(s)"
        return result
    with path.open("rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        scanner = _Scanner(mm, path, parse, result)
        try:
            pos = scanner.preamble()
            if start_offset is not None:
                pos, scanner.next_id = start_offset, start_item_id
            scanner.walk(pos)
        finally:
            scanner.close()
    return result


def repair_tail(result: ScanResult) -> None:
    """Make a scanned segment a complete MCAP file: cut a torn tail (keeping the cut bytes in
    `<name>.tail-<offset>.bad`) and append DataEnd + Footer. Damaged bytes elsewhere stay in place (the
    next scan skips them the same way). A file too short to hold a preamble is left as it is."""
    path = result.path
    if result.finished or result.file_size < len(MAGIC):
        return
    if result.torn:
        with path.open("rb") as fh:
            fh.seek(result.good_end)
            tail = fh.read()
        path.with_name(f"{path.name}.tail-{result.good_end}.bad").write_bytes(tail)
    with path.open("r+b") as fh:
        fh.truncate(result.good_end)
        fh.seek(result.good_end)
        fh.write(SEGMENT_TRAILER)
        fh.flush()
        os.fsync(fh.fileno())
    fsync_directory(path.parent)
