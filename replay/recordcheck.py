"""Per-record checksums of the replay log: each stored transition carries a CRC-32 of its own bytes.

A chunk's CRC (log.py) says only that something in the chunk is wrong; to keep every intact record of a
damaged chunk, and to find damage in a segment that recovery no longer scans (its items are in a
snapshot), each record must be checkable alone. The check is a protobuf field appended to the stored
Transition, as the priority suffix is: field 2047 (kept out of romannet.proto, so no message ever sets
it), fixed32, holding CRC-32 over the item id (8 bytes, little-endian) and every stored byte before the
field. Binding the id catches a record that is intact but sits where another item is expected. Readers
that decode the Transition (the learner, MCAP tools) keep it as an unknown field and ignore it.
"""

from __future__ import annotations

import struct
import zlib

CHECK_FIELD = 2047
_TAG = bytes([((CHECK_FIELD << 3) | 5) & 0x7F | 0x80, (CHECK_FIELD << 3) >> 7])  # varint, wire type 5
CHECK_BYTES = len(_TAG) + 4


def record_crc(item_id: int, parts: tuple[bytes | memoryview, ...]) -> int:
    """CRC-32 over the item id and the record's bytes (given in parts, so no joined copy is made)."""
    crc = zlib.crc32(struct.pack("<Q", item_id))
    for part in parts:
        crc = zlib.crc32(part, crc)
    return crc


def check_suffix(item_id: int, *parts: bytes | memoryview) -> bytes:
    """The bytes to append to a record made of `parts` so that record_problem() can check it."""
    return _TAG + struct.pack("<I", record_crc(item_id, parts))


def record_problem(item_id: int, data: bytes | bytearray | memoryview) -> str | None:
    """None if `data` (a stored record, check field included) is intact for `item_id`, else why not."""
    view = memoryview(data)
    if len(view) < CHECK_BYTES or bytes(view[-CHECK_BYTES:-4]) != _TAG:
        return f"item {item_id}: the record has no checksum field at its end (damaged)"
    (stored,) = struct.unpack("<I", view[-4:])
    if record_crc(item_id, (view[:-CHECK_BYTES],)) != stored:
        return f"item {item_id}: the record fails its checksum (damaged bytes)"
    return None
