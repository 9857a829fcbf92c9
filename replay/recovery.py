"""Restart = latest snapshot + log tail: rebuild the replay index from a store directory.

The snapshot lists the items held when it was taken (ids, priorities, where their bytes are) and where
the log continues; the tail scan adds every item logged after it, with the priority it was inserted with
(log records carry it as the Transition's initial_priority). Priority updates after the last snapshot
are not logged, so those items get their snapshot (or insert) priority back.

Item ids are consecutive, so what is missing is exact: a snapshot item whose segment is gone or cut
short, a gap between the ids found on either side of damaged bytes or of a missing segment, and ids
named by damaged records at the end of the log. Each becomes a Loss (losses.py) with its ids; the store
refuses to go on over one that no operator has accepted. A chunk torn by a crash at the very end of the
log was never acknowledged: a warning, not a loss. Scanning (`scan_directory`) writes nothing, so
`romannet replay --check` can use it; `repair` then makes every segment a complete MCAP file again.
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
from .losses import Loss, to_ranges
from .segscan import ScanResult, repair_tail, scan_segment
from .snapshot import load_latest, snapshot_files

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
    dropped_bytes: int = 0  # of torn tails (never acknowledged)
    dropped_records: int = 0
    seconds: float = 0.0
    losses: list[Loss] = field(default_factory=list)  # acknowledged items that cannot be recovered
    scans: list[ScanResult] = field(default_factory=list)


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


def _from_snapshot(arrays: dict[str, np.ndarray], meta: dict[str, Any], sizes: dict[int, int],
                   reclaimed_below: int) -> tuple[list, list[Loss]]:
    """Snapshot items whose bytes are still on disk, and a Loss per segment that lost some of them.
    Segments below `reclaimed_below` may have been reclaimed on purpose after a newer snapshot that is
    now unreadable; their items are dropped without a loss."""
    actors, episodes = meta["actors"], meta["episodes"]
    items = []
    gone: dict[int, list[int]] = {}
    columns = zip(arrays["item_id"].tolist(), arrays["segment"].tolist(), arrays["chunk_offset"].tolist(),
                  arrays["chunk_first_id"].tolist(), arrays["data_offset"].tolist(), arrays["length"].tolist(),
                  arrays["priority"].tolist(), arrays["policy_version"].tolist(), arrays["actor"].tolist(),
                  arrays["episode"].tolist(), arrays["step"].tolist(), strict=True)
    for item_id, seg, c_off, c_first, d_off, length, prio, pv, actor, episode, step in columns:
        if seg not in sizes and seg < reclaimed_below:
            continue
        if d_off + length > sizes.get(seg, -1):
            gone.setdefault(seg, []).append(item_id)
            continue
        items.append((item_id, Location(seg, c_off, c_first, d_off, length),
                      ItemMeta((actors[actor], episodes[episode], step), prio, pv)))
    losses = [Loss("lost", _segment_problem(seg, sizes), to_ranges(ids)) for seg, ids in sorted(gone.items())]
    return items, losses


def _segment_problem(number: int, sizes: dict[int, int]) -> str:
    name = f"segment-{number:06d}.mcap"
    if number not in sizes:
        return f"{name} is missing"
    return f"{name} is empty" if sizes[number] == 0 else f"{name} is cut short to {sizes[number]} bytes"


def _warn_torn(scan: ScanResult) -> None:
    log.warning("replay log %s: dropped %d byte(s) of a chunk torn by a crash at offset %d (about %d "
                "transition record(s)); it was never acknowledged, so nothing acknowledged is lost",
                scan.path.name, scan.dropped_bytes, scan.good_end, scan.torn_records)


def _damage_where(scan: ScanResult) -> str:
    spots = ", ".join(f"offset {d.offset}-{d.end}" for d in scan.damage[:4])
    more = f" and {len(scan.damage) - 4} more" if len(scan.damage) > 4 else ""
    return f"damaged bytes in {scan.path.name} at {spots}{more}: {scan.damage[0].reason}"


class _TailAccount:
    """Walks the scanned segments in order and names every id that should be there and is not."""

    def __init__(self, expected: int | None, prev_number: int | None):
        self.expected = expected  # the next id the log should hold
        self.prev_number = prev_number
        self.losses: list[Loss] = []
        self.carry: str | None = None  # why the ids up to the next segment's first are missing

    def segment(self, number: int, scan: ScanResult, fresh: list[int]) -> None:
        """Account for one scanned segment whose new items (ids at or above the snapshot's) are `fresh`."""
        missing = [] if self.prev_number is None else list(range(self.prev_number + 1, number))
        self.prev_number = number
        if missing:
            self.carry = ", ".join(f"segment-{n:06d}.mcap" for n in missing) + " missing"
        first = scan.first_item_id if scan.first_item_id is not None else (fresh[0] if fresh else None)
        if first is not None and self.expected is not None and first > self.expected:
            what = self.carry or f"the start of {scan.path.name} is damaged"
            self.losses.append(Loss("lost", what, ((self.expected, first),)))
            self.expected = first
        self.carry = None
        gaps = []
        for item_id in fresh:
            if self.expected is not None and item_id > self.expected:
                gaps.append((self.expected, item_id))
            self.expected = item_id + 1
        last_offset = scan.items[-1][1].data_offset if scan.items else -1
        tail = [d for d in scan.damage if d.offset > last_offset]  # damage after the last good record
        named = sorted(i for d in tail for i in d.named_ids if self.expected is None or i >= self.expected)
        if named and self.expected is not None:
            gaps.append((self.expected, named[-1] + 1))
            self.expected = named[-1] + 1
        if gaps:
            what = _damage_where(scan) if scan.damage else f"records missing from {scan.path.name}"
            self.losses.append(Loss("lost", what, tuple(gaps)))
        if tail:
            self.carry = _damage_where(scan)  # the next segment's first id tells how many more
        if first is None and not fresh:
            self.carry = f"{scan.path.name} is unreadable ({scan.preamble_problem})"

    def end(self) -> None:
        """After the newest segment: damage at its end hides how many items were logged there after the
        newest snapshot (the description stays the same on every scan, so an accepted loss is known)."""
        if self.carry is None:
            return
        last = self.losses[-1] if self.losses else None
        if last is not None and last.what == self.carry:
            self.losses[-1] = Loss(last.kind, last.what, last.ranges, uncounted=True)
        else:
            self.losses.append(Loss("lost", self.carry, (), uncounted=True))


def scan_directory(directory: Path, clean: bool = True) -> Recovered:
    """Read the newest usable snapshot and scan the log after it; writes nothing (but leftover snapshot
    .tmp files are removed when `clean`)."""
    t0 = time.perf_counter()
    out = Recovered()
    segments = list_segments(directory)
    sizes = {segment_number(p): p.stat().st_size for p in segments}
    newest_file = (snapshot_files(directory) or [None])[-1]
    loaded = load_latest(directory, clean=clean)
    start: tuple[int, int, int] | None = None  # (segment, chunk offset, chunk's first item id)
    expected: int | None = None if newest_file is not None else 0  # a directory without snapshots starts at 0
    prev_number: int | None = None if newest_file is not None else 0
    if loaded is not None:
        out.snapshot, meta, arrays = loaded
        reclaimable = min(sizes, default=0) if out.snapshot != newest_file else 0
        out.items, out.losses = _from_snapshot(arrays, meta, sizes, reclaimable)
        out.next_item_id = expected = int(meta["next_item_id"])
        out.counters = meta["counters"]
        if meta.get("scan_from") is not None:
            start = tuple(meta["scan_from"])  # type: ignore[assignment]
            prev_number = start[0] - 1  # type: ignore[index]
    account = _TailAccount(expected, prev_number)
    for path in segments:
        number = segment_number(path)
        if start is not None and number < start[0]:
            continue
        if start is not None and number == start[0]:
            scan = scan_segment(path, parse_record, start[1], start[2])
        else:
            scan = scan_segment(path, parse_record)
        out.scans.append(scan)
        fresh = [it for it in scan.items if it[0] >= out.next_item_id]
        account.segment(number, scan, [it[0] for it in fresh])
        out.items.extend(fresh)
        out.tail_items += len(fresh)
        if fresh:
            out.next_item_id = fresh[-1][0] + 1
        if scan.torn:
            _warn_torn(scan)
            out.dropped_bytes += scan.dropped_bytes
            out.dropped_records += scan.torn_records
    if start is not None and start[0] not in sizes and account.prev_number == start[0] - 1:
        account.carry = f"segment-{start[0]:06d}.mcap missing"  # the newest segment, and nothing after it
    account.end()
    out.losses += account.losses
    if account.expected is not None:
        out.next_item_id = max(out.next_item_id, account.expected)  # never reuse the id of a lost item
    out.seconds = time.perf_counter() - t0
    return out


def repair(directory: Path, rec: Recovered) -> None:
    """Make every scanned segment a complete MCAP file (cut torn tails, append trailers); remove segment
    files a crash left half-created."""
    for scan in rec.scans:
        if not scan.finished:
            repair_tail(scan)
    for leftover in directory.glob("segment-*.mcap.new"):
        log.info("removing %s: a segment a crash left half-created (it held nothing)", leftover.name)
        leftover.unlink()


def recover(directory: Path) -> Recovered:
    """scan_directory, then repair (callers that must refuse a loss first use the two steps)."""
    rec = scan_directory(directory)
    repair(directory, rec)
    log_summary(rec)
    return rec


def log_summary(rec: Recovered) -> None:
    if rec.scans or rec.snapshot is not None:
        lost = sum(loss.count for loss in rec.losses)
        log.info("replay recovered %d item(s) in %.2f s: snapshot %s + %d from the log tail%s%s",
                 len(rec.items), rec.seconds, rec.snapshot.name if rec.snapshot else "none", rec.tail_items,
                 f"; dropped a torn tail of {rec.dropped_bytes} bytes" if rec.dropped_bytes else "",
                 f"; {lost} acknowledged item(s) lost" if rec.losses else "")
