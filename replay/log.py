"""Durable append-only transition log: MCAP segment files `segment-000001.mcap`, ... in one directory.

Each segment is a standard MCAP file (readable by the mcap CLI, Foxglove, mcap's Python readers):
magic, Header, Schema (romannet.v1.Transition, protobuf, from wire.mcap_schema()), Channel "/replay/
transitions" whose metadata holds `first_item_id`, then one Chunk (uncompressed: the PNGs are compressed
already; with a CRC) per group commit holding Message records. A message's data is the encoded
Transition, its sequence the item id mod 2^32 (a check), log_time the time it was received (ns since the
Unix epoch), publish_time the transition's end_ns. Item ids in a segment are consecutive from
first_item_id, so ids need no extra field. A segment being written has no footer until it is rotated or
closed; recovery finishes unfinished segments (DataEnd + Footer) so they become complete files.

Group commit: `append` queues a record; `sync(ticket)` writes everything queued as one chunk and fsyncs,
so concurrent inserters share one fsync. Chunk boundaries are the unit of durability: a chunk torn by
a crash (never acknowledged) is dropped whole. Each record also carries its own checksum (recordcheck.py;
segments whose Header names the library `romannet.replay/2`), so damage costs only the damaged records:
recovery resynchronises at the next good record (segscan.py) and every read can be checked.

A new segment is written under a temporary name and renamed once its preamble is durable, so a segment
file that is empty or lacks its preamble is always damage, never a crash while rotating.
"""

from __future__ import annotations

import logging
import os
import struct
import threading
import time
import zlib
from dataclasses import dataclass
from pathlib import Path

from romannet.common.fsutil import fsync_directory
from romannet.common.wire import mcap_schema

from .recordcheck import check_suffix

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_DATA_END = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F
TOPIC = "/replay/transitions"
PROFILE = "romannet-replay"
LIBRARY = "romannet.replay/2"  # records end with a checksum field (recordcheck.py)
LEGACY_LIBRARY = "romannet.replay"  # records without one (older directories): checked per chunk only
CHUNK_FIXED_BYTES = 9 + 8 + 8 + 8 + 4 + 4 + 8  # record header + chunk fields with compression ""
MESSAGE_FIXED_BYTES = 9 + 2 + 4 + 8 + 8  # record header + channel, sequence, log_time, publish_time
SEGMENT_GLOB = "segment-*.mcap"


def segment_path(directory: Path, number: int) -> Path:
    return directory / f"segment-{number:06d}.mcap"


def segment_number(path: Path) -> int:
    return int(path.stem.split("-")[1])


def list_segments(directory: Path) -> list[Path]:
    """Segment files in log order."""
    paths = [p for p in directory.glob(SEGMENT_GLOB) if p.stem.split("-")[1].isdigit()]
    return sorted(paths, key=segment_number)


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body


def _string(text: str) -> bytes:
    raw = text.encode()
    return struct.pack("<I", len(raw)) + raw


def _string_map(values: dict[str, str]) -> bytes:
    body = b"".join(_string(k) + _string(v) for k, v in sorted(values.items()))
    return struct.pack("<I", len(body)) + body


def segment_preamble(first_item_id: int) -> bytes:
    """Magic, Header, Schema and Channel of a new segment."""
    name, encoding, data = mcap_schema("Transition")
    schema = _record(OP_SCHEMA, struct.pack("<H", 1) + _string(name) + _string(encoding)
                     + struct.pack("<I", len(data)) + data)
    channel = _record(OP_CHANNEL, struct.pack("<HH", 1, 1) + _string(TOPIC) + _string("protobuf")
                      + _string_map({"first_item_id": str(first_item_id)}))
    return MAGIC + _record(OP_HEADER, _string(PROFILE) + _string(LIBRARY)) + schema + channel


def is_legacy_segment(path: Path) -> bool:
    """True if the segment's Header names the library that wrote records without checksums."""
    try:
        with path.open("rb") as fh:
            head = fh.read(64)
    except OSError:
        return False
    legacy = _record(OP_HEADER, _string(PROFILE) + _string(LEGACY_LIBRARY))
    return head[8:8 + len(legacy)] == legacy


# DataEnd (no data CRC) + Footer without a summary section + closing magic.
SEGMENT_TRAILER = (_record(OP_DATA_END, struct.pack("<I", 0)) + _record(OP_FOOTER, struct.pack("<QQI", 0, 0, 0))
                   + MAGIC)



def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _writev_all(fd: int, parts: list[bytes]) -> None:
    """os.writev until everything is written (it may write less, and takes at most IOV_MAX buffers)."""
    views = [memoryview(p) for p in parts if p]
    while views:
        written = os.writev(fd, views[:512])
        while written:
            n = min(written, len(views[0]))
            written -= n
            views[0] = views[0][n:]
            if not views[0]:
                views.pop(0)


@dataclass(frozen=True)
class Location:
    """Where an item's encoded transition lies: segment number, byte offsets in that file, length."""

    segment: int
    chunk_offset: int  # the chunk holding the item (where a recovery scan may start)
    chunk_first_id: int  # id of the chunk's first item
    data_offset: int
    length: int


@dataclass
class _Pending:
    ticket: int
    item_id: int
    data: bytes
    suffix: bytes  # appended to data on disk (kept apart to save a copy of the PNG bytes)
    log_time_ns: int
    publish_time_ns: int

    @property
    def length(self) -> int:
        return len(self.data) + len(self.suffix)


class LogFailed(OSError):
    """An earlier write or fsync failed; nothing more is acknowledged until the store is reopened."""


class SegmentLog:
    """Appends chunks of transitions to the newest segment; thread-safe; group commit."""

    def __init__(self, directory: Path, segment_max_bytes: int, fsync: bool = True):
        self.directory = directory
        self.segment_max_bytes = segment_max_bytes
        self.fsync_enabled = fsync
        self._mu = threading.Lock()  # queue and tickets
        self._commit_mu = threading.Lock()  # one writer at a time
        self._pending: list[_Pending] = []
        self._next_ticket = 1
        self._durable_ticket = 0
        self._durable: list[tuple[int, Location]] = []
        self._failed: BaseException | None = None
        self._fd: int | None = None
        self._segment = 0
        self._size = 0
        self._chunks_in_segment = 0
        self._readers: dict[int, int] = {}
        self._readers_mu = threading.Lock()
        self.fsyncs = 0
        existing = list_segments(directory)
        self._last_number = segment_number(existing[-1]) if existing else 0

    # ---------------------------------------------------------------------------------------- writing
    def append(self, item_id: int, data: bytes, publish_time_ns: int, suffix: bytes = b"") -> int:
        """Queue a record (its bytes: data + suffix + its checksum); returns the ticket to pass to sync()."""
        suffix = suffix + check_suffix(item_id, data, suffix)  # outside the lock: inserters run it in parallel
        with self._mu:
            if self._failed is not None:
                raise LogFailed(f"the replay log failed earlier ({self._failed}); restart the server")
            ticket = self._next_ticket
            self._next_ticket += 1
            self._pending.append(_Pending(ticket, item_id, data, suffix, time.time_ns(), publish_time_ns))
            return ticket

    def sync(self, ticket: int) -> None:
        """Return once the record with `ticket` (and every earlier one) is written and fsync'ed."""
        with self._commit_mu:
            with self._mu:
                if self._failed is not None:
                    raise LogFailed(f"the replay log failed ({self._failed}); restart the server")
                if self._durable_ticket >= ticket:
                    return  # a concurrent commit covered us
                batch, self._pending = self._pending, []  # group commit: every insert waiting now
            try:
                written = self._write_chunk(batch)
            except BaseException as exc:
                with self._mu:
                    self._failed = exc
                raise
            with self._mu:
                self._durable_ticket = batch[-1].ticket
                self._durable.extend(written)

    def pop_durable(self) -> list[tuple[int, Location]]:
        """(item id, location) of records made durable since the last call, in id order."""
        with self._mu:
            out, self._durable = self._durable, []
            return out

    def _write_chunk(self, batch: list[_Pending]) -> list[tuple[int, Location]]:
        parts: list[bytes] = []
        size = 0
        crc = 0
        offsets = []
        for p in batch:
            head = struct.pack("<BQHIQQ", OP_MESSAGE, MESSAGE_FIXED_BYTES - 9 + p.length, 1,
                               p.item_id & 0xFFFFFFFF, p.log_time_ns, p.publish_time_ns)
            offsets.append(size + len(head))
            for part in (head, p.data, p.suffix):
                parts.append(part)
                crc = zlib.crc32(part, crc)
            size += len(head) + p.length
        times = [p.log_time_ns for p in batch]
        if self._fd is None or (self._size + CHUNK_FIXED_BYTES + size > self.segment_max_bytes
                                and self._chunks_in_segment > 0):
            self._rotate(batch[0].item_id)
        header = struct.pack("<BQQQQII", OP_CHUNK, CHUNK_FIXED_BYTES - 9 + size, min(times), max(times), size,
                             crc, 0) + struct.pack("<Q", size)
        chunk_offset = self._size
        assert self._fd is not None
        _writev_all(self._fd, [header, *parts])  # no joined copy of the (large) transitions
        self._size += len(header) + size
        self._chunks_in_segment += 1
        if self.fsync_enabled:
            os.fsync(self._fd)
            self.fsyncs += 1
        base = chunk_offset + CHUNK_FIXED_BYTES
        first = batch[0].item_id
        return [(p.item_id, Location(self._segment, chunk_offset, first, base + off, p.length))
                for p, off in zip(batch, offsets, strict=True)]

    def _rotate(self, first_item_id: int) -> None:
        """Finish the current segment (if any) and start the next one, durably."""
        self._finish_current()
        self._last_number += 1
        path = segment_path(self.directory, self._last_number)
        tmp = path.with_name(path.name + ".new")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        preamble = segment_preamble(first_item_id)
        _write_all(fd, preamble)
        if self.fsync_enabled:
            os.fsync(fd)
        if path.exists():
            os.close(fd)
            raise FileExistsError(f"{path} exists already")
        os.rename(tmp, path)  # the name appears only with its preamble
        if self.fsync_enabled:
            fsync_directory(self.directory)  # the new name must survive a crash too
        self._fd, self._segment, self._size = fd, self._last_number, len(preamble)
        self._chunks_in_segment = 0
        log.debug("opened %s (first item %d)", path.name, first_item_id)

    def _finish_current(self) -> None:
        if self._fd is None:
            return
        _write_all(self._fd, SEGMENT_TRAILER)
        if self.fsync_enabled:
            os.fsync(self._fd)
        os.close(self._fd)
        self._fd = None

    def close(self) -> None:
        """Write what is queued, finish the segment (a complete MCAP file) and close it."""
        with self._mu:
            last = self._next_ticket - 1
        if last > self._durable_ticket and self._failed is None:
            self.sync(last)
        with self._commit_mu:
            if self._failed is None:
                self._finish_current()
            elif self._fd is not None:
                os.close(self._fd)
                self._fd = None
        with self._readers_mu:
            for fd in self._readers.values():
                os.close(fd)
            self._readers.clear()

    @property
    def current_segment(self) -> int:
        """Number of the segment being written (0 before the first write)."""
        return self._segment

    # ---------------------------------------------------------------------------------------- reading
    def _reader(self, segment: int) -> int:
        with self._readers_mu:
            fd = self._readers.get(segment)
            if fd is None:
                fd = os.open(segment_path(self.directory, segment), os.O_RDONLY)
                self._readers[segment] = fd
            return fd

    def read(self, loc: Location) -> bytes:
        """The stored bytes of one item (from the page cache when recent)."""
        data = os.pread(self._reader(loc.segment), loc.length, loc.data_offset)
        if len(data) != loc.length:
            raise OSError(f"short read of {loc}: {len(data)} bytes")
        return data

    def read_into(self, loc: Location, out: memoryview) -> None:
        """read(), straight into `out` (exactly loc.length bytes long): no bytes object in between."""
        if len(out) != loc.length:
            raise ValueError(f"buffer of {len(out)} bytes for an item of {loc.length}")
        n = os.preadv(self._reader(loc.segment), [out], loc.data_offset)
        if n != loc.length:
            raise OSError(f"short read of {loc}: {n} bytes")

    def delete_segments_below(self, segment: int) -> list[int]:
        """Delete finished segments numbered below `segment` (their items are all evicted)."""
        deleted = []
        for path in list_segments(self.directory):
            number = segment_number(path)
            if number >= segment or number == self._segment:
                continue
            with self._readers_mu:
                fd = self._readers.pop(number, None)
            if fd is not None:
                os.close(fd)
            path.unlink()
            deleted.append(number)
        if deleted:
            fsync_directory(self.directory)
            log.info("reclaimed %d fully evicted log segment(s): %s", len(deleted), deleted)
        return deleted
