"""Reading a drawn batch out of the replay log, each record checked as it is read: as a list of bytes
(ReplayStore.sample) or straight into its place in the protobuf reply (ReplayStore.sample_encoded). Each
returns the damaged items it met (id -> why) so the store can quarantine them and draw again.

Apart from replay/store.py so the store keeps to its index and the rules of drawing a batch.
"""

from __future__ import annotations

from collections.abc import Callable

from .batchcodec import sample_batch_layout
from .log import Location, SegmentLog

Drawn = list[tuple[int, float, float, Location]]  # (id, P(i), IS weight, location) per item of a batch
Problem = Callable[[int, Location, bytes | memoryview], str | None]  # why a record is damaged, or None


def read_batch(log: SegmentLog, drawn: Drawn, problem: Problem) -> tuple[list[bytes], dict[int, str]]:
    """The drawn records' bytes (b"" for an unreadable one) and the damaged ones met."""
    datas, bad = [], {}
    for item_id, _, _, loc in drawn:
        try:
            datas.append(log.read(loc))
        except OSError as exc:
            datas.append(b"")
            bad[item_id] = f"item {item_id}: unreadable ({exc})"
            continue
        found = problem(item_id, loc, datas[-1])
        if found:
            bad[item_id] = found
    return datas, bad


def read_batch_encoded(log: SegmentLog, request_id: str, size: int, drawn: Drawn,
                       problem: Problem) -> tuple[bytearray, dict[int, str]]:
    """The SampleBatch reply for the drawn records (buffer size `size`), each record read from the log
    into its place (batchcodec), and the damaged ones met."""
    buf, offsets = sample_batch_layout(request_id, size, [(i, p, w, loc.length) for i, p, w, loc in drawn])
    view = memoryview(buf)
    bad = {}
    for (item_id, _, _, loc), off in zip(drawn, offsets, strict=True):
        hole = view[off:off + loc.length]
        try:
            log.read_into(loc, hole)
        except OSError as exc:
            bad[item_id] = f"item {item_id}: unreadable ({exc})"
            continue
        found = problem(item_id, loc, hole)
        if found:
            bad[item_id] = found
    return buf, bad
