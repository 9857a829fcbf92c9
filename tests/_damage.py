"""Damaging real episode files the way disks and copies do: a flipped byte in a chunk, in a record's
length, in the metadata; a cut file; a zeroed footer or summary; a file that is not MCAP at all.

Offsets are found by walking the file's records (opcode, length, body) as MCAP lays them out, never at a
fixed share of the file, so a damage lands where it is meant to whatever the recorded sizes are.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

OP_METADATA, OP_CHUNK, OP_DATA_END, OP_FOOTER = 0x0C, 0x06, 0x0F, 0x02
MAGIC = 8
HEADER = 9  # opcode (1) + record length (8)


@dataclass(frozen=True)
class Record:
    offset: int
    opcode: int
    length: int  # of the body

    @property
    def body(self) -> int:
        return self.offset + HEADER

    @property
    def end(self) -> int:
        return self.body + self.length


def records(data: bytes) -> list[Record]:
    """Every record of an intact file, data section and summary, up to and including the footer."""
    out, offset = [], MAGIC
    while offset + HEADER <= len(data) - MAGIC:
        rec = Record(offset, data[offset], int.from_bytes(data[offset + 1:offset + HEADER], "little"))
        out.append(rec)
        offset = rec.end
        if rec.opcode == OP_FOOTER:
            break
    return out


def chunks(data: bytes) -> list[Record]:
    return [r for r in records(data) if r.opcode == OP_CHUNK]


def chunk_payload(data: bytes, chunk: Record) -> tuple[int, int]:
    """(start, end) of a chunk's compressed records: the bytes its CRC covers once decompressed."""
    # Chunk body: start time (8), end time (8), uncompressed size (8), CRC (4), compression string
    # (4 + n), records length (8), records.
    comp_len = int.from_bytes(data[chunk.body + 28:chunk.body + 32], "little")
    start = chunk.body + 32 + comp_len + 8
    return start, chunk.end


def flipped(data: bytes, at: int) -> bytes:
    out = bytearray(data)
    out[at] ^= 0xFF
    return bytes(out)


def zeroed(data: bytes, start: int, end: int) -> bytes:
    return data[:start] + b"\x00" * (end - start) + data[end:]


def flip_in_chunk(data: bytes, index: int) -> bytes:
    """A byte in the middle of chunk `index`'s compressed records: its CRC (or decompression) fails."""
    start, end = chunk_payload(data, chunks(data)[index])
    return flipped(data, (start + end) // 2)


def flip_chunk_length(data: bytes, index: int) -> bytes:
    """The high byte of chunk `index`'s record length: the record now claims to run past the file's end,
    so the records after it can only be found again by their chunk index or by scanning."""
    return flipped(data, chunks(data)[index].offset + 8)


def flip_in_metadata(data: bytes, which: int = 0) -> bytes:
    """A byte of the `which`-th metadata record's name length: the record no longer parses."""
    meta = [r for r in records(data) if r.opcode == OP_METADATA][which]
    return flipped(data, meta.body + 3)


def summary_start(data: bytes) -> int:
    return next(r for r in records(data) if r.opcode == OP_DATA_END).end


def zero_footer(data: bytes) -> bytes:
    footer = next(r for r in records(data) if r.opcode == OP_FOOTER)
    return zeroed(data, footer.offset, len(data))


def zero_summary(data: bytes) -> bytes:
    """The summary records zeroed (the footer still points at them, its CRC no longer matches)."""
    footer = next(r for r in records(data) if r.opcode == OP_FOOTER)
    return zeroed(data, summary_start(data), footer.offset)


def cut(data: bytes, fraction: float) -> bytes:
    return data[:int(len(data) * fraction)]


def write(path: Path, data: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path
