"""Restart = latest snapshot + log tail: rebuild the replay index from a store directory.

The snapshot lists the items held when it was taken (ids, priorities, where their bytes are) and where
the log continues; the tail scan adds every item logged after it, with the priority it was inserted with
(log records carry it as the Transition's initial_priority). Priority updates after the last snapshot
are not logged, so those items get their snapshot (or insert) priority back. Segments are scanned in
order; a torn or corrupt chunk ends its segment's scan, with a warning saying how much was dropped, and
the file is repaired (segscan.repair_tail) so the log can go on.
"""

from __future__ import annotations

import logging
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from google.protobuf import message as pb_message

from romannet.common import romannet_pb2 as pb

from .log import Location, list_segments, segment_number
from .segscan import ScanResult, repair_tail, scan_segment
from .snapshot import load_latest

log = logging.getLogger(__name__)

Key = tuple[str, str, int]  # (actor id, episode id, step): the idempotency key


@dataclass
class ItemMeta:
    """What the index keeps per item besides its location."""

    key: Key
    priority: float
    policy_version: int


@dataclass
class Recovered:
    """An index rebuilt from disk; items in id order (the store applies capacity while adding them)."""

    items: list[tuple[int, Location, ItemMeta]] = field(default_factory=list)
    next_item_id: int = 0
    counters: dict[str, Any] = field(default_factory=dict)
    snapshot: Path | None = None
    tail_items: int = 0
    dropped_bytes: int = 0
    dropped_records: int = 0
    seconds: float = 0.0


def priority_suffix(priority: float) -> bytes:
    """Protobuf bytes of Transition.initial_priority (field 23, 64-bit): appended to a stored record it
    overrides any earlier value (a later singular field wins), so the log says what priority was used."""
    return b"\xb9\x01" + struct.pack("<d", priority)


def parse_record(data: memoryview) -> ItemMeta:
    """The index fields of a logged Transition (PNG bytes are not decoded); ValueError if unreadable."""
    t = pb.Transition()
    try:
        t.ParseFromString(bytes(data))
    except pb_message.DecodeError as exc:
        raise ValueError(f"not a Transition record ({exc})") from exc
    if not t.actor_id or not t.episode_id or not t.HasField("step") or not t.HasField("initial_priority"):
        raise ValueError("Transition record lacks actor_id, episode_id, step or initial_priority")
    return ItemMeta((t.actor_id, t.episode_id, t.step), t.initial_priority, t.policy_version)


def _from_snapshot(arrays: dict[str, np.ndarray], meta: dict[str, Any], existing: set[int]) -> list:
    actors, episodes = meta["actors"], meta["episodes"]
    items = []
    columns = zip(arrays["item_id"].tolist(), arrays["segment"].tolist(), arrays["chunk_offset"].tolist(),
                  arrays["chunk_first_id"].tolist(), arrays["data_offset"].tolist(), arrays["length"].tolist(),
                  arrays["priority"].tolist(), arrays["policy_version"].tolist(), arrays["actor"].tolist(),
                  arrays["episode"].tolist(), arrays["step"].tolist(), strict=True)
    for item_id, seg, c_off, c_first, d_off, length, prio, pv, actor, episode, step in columns:
        if seg not in existing:  # reclaimed after this snapshot was taken (a newer one was unreadable)
            continue
        items.append((item_id, Location(seg, c_off, c_first, d_off, length),
                      ItemMeta((actors[actor], episodes[episode], step), prio, pv)))
    return items


def _warn_dropped(scan: ScanResult, last: bool) -> None:
    where = "tail" if last else "middle (a later segment follows)"
    log.warning("replay log %s: dropped %d byte(s) at the %s of the segment from offset %d, holding about %d "
                "transition record(s): %s. %s", scan.path.name, scan.dropped_bytes, where, scan.good_end,
                scan.dropped_records, scan.problem,
                "A torn final chunk was never acknowledged." if last else "Acknowledged data may be lost.")


def recover(directory: Path) -> Recovered:
    """Read the newest usable snapshot and scan the log after it; repairs torn segment tails."""
    t0 = time.perf_counter()
    out = Recovered()
    segments = list_segments(directory)
    existing = {segment_number(p) for p in segments}
    loaded = load_latest(directory)
    start: tuple[int, int, int] | None = None  # (segment, chunk offset, chunk's first item id)
    if loaded is not None:
        out.snapshot, meta, arrays = loaded
        out.items = _from_snapshot(arrays, meta, existing)
        out.next_item_id = int(meta["next_item_id"])
        out.counters = meta["counters"]
        if meta.get("scan_from") is not None and meta["scan_from"][0] in existing:
            start = tuple(meta["scan_from"])  # type: ignore[assignment]
    for i, path in enumerate(segments):
        number = segment_number(path)
        if start is not None and number < start[0]:
            continue
        if start is not None and number == start[0]:
            scan = scan_segment(path, parse_record, start[1], start[2])
        else:
            scan = scan_segment(path, parse_record)
        fresh = [it for it in scan.items if it[0] >= out.next_item_id]
        out.items.extend(fresh)
        out.tail_items += len(fresh)
        if fresh:
            out.next_item_id = fresh[-1][0] + 1
        if not scan.finished:
            if scan.dropped_bytes:
                _warn_dropped(scan, last=i == len(segments) - 1)
                out.dropped_bytes += scan.dropped_bytes
                out.dropped_records += scan.dropped_records
            repair_tail(scan)
    out.seconds = time.perf_counter() - t0
    if segments or loaded is not None:
        log.info("replay recovered %d item(s) in %.2f s: snapshot %s + %d from the log tail%s",
                 len(out.items), out.seconds, out.snapshot.name if out.snapshot else "none", out.tail_items,
                 f"; dropped {out.dropped_bytes} bytes" if out.dropped_bytes else "")
    return out
