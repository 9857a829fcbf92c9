"""The replay directory's damage record, `losses.json`: acknowledged items recovery could not get back,
and items quarantined because their bytes were found damaged.

Why a file of its own: once a new snapshot is written, nothing else on disk says that items were lost
(the snapshot simply no longer lists them), so the loss would be sealed silently. Recovery therefore
refuses to go on over a loss that this file does not list yet, until an operator accepts it
(`romannet replay --accept-loss`); accepting writes it here first, before any snapshot. Quarantined items
are written here as they are found, so a restart from an older snapshot does not offer them again.
The file is rewritten atomically (tmp, fsync, rename, fsync of the directory); ids are kept as ranges.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from romannet.common.errors import RomannetError
from romannet.common.fsutil import fsync_directory

FILE = "losses.json"
_FORMAT = 1
Range = tuple[int, int]  # [start, end) of item ids


class ReplayLossError(RomannetError):
    """Acknowledged items cannot be recovered and no operator has accepted the loss yet."""


@dataclass(frozen=True)
class Loss:
    """Items gone for one reason: kind 'lost' (recovery) or 'quarantined' (damaged when read)."""

    kind: str
    what: str  # where and why, e.g. "segment-000002.mcap is missing"
    ranges: tuple[Range, ...] = ()
    uncounted: bool = False  # more may be gone than `ranges` names: nothing left on disk names them

    @property
    def count(self) -> int:
        return sum(end - start for start, end in self.ranges)


def to_ranges(ids: Iterable[int]) -> tuple[Range, ...]:
    """Sorted, merged [start, end) ranges of the given ids."""
    return merge_ranges((i, i + 1) for i in ids)


def merge_ranges(ranges: Iterable[Range]) -> tuple[Range, ...]:
    """Sorted ranges with overlapping and touching ones joined."""
    out: list[list[int]] = []
    for a, b in sorted(ranges):
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return tuple((a, b) for a, b in out)


def format_ranges(ranges: Sequence[Range], limit: int = 12) -> str:
    """'3, 7-9, 12' (at most `limit` ranges, then how many more)."""
    parts = [str(a) if b == a + 1 else f"{a}-{b - 1}" for a, b in ranges[:limit]]
    if len(ranges) > limit:
        parts.append(f"and {len(ranges) - limit} more range(s)")
    return ", ".join(parts)


def describe(loss: Loss) -> str:
    """One phrase: how many, which ids, where and why."""
    if not loss.ranges:
        return f"an uncounted number of items ({loss.what}; items logged there after the newest snapshot " \
               "cannot be counted)"
    more = " and possibly more" if loss.uncounted else ""
    return f"{loss.count} item(s){more} (ids {format_ranges(loss.ranges)}; {loss.what})"


def _contains(ranges: Sequence[Range], inner: Range) -> bool:
    return any(a <= inner[0] and inner[1] <= b for a, b in ranges)


def unaccepted(found: Sequence[Loss], recorded: Sequence[Loss]) -> list[Loss]:
    """The losses in `found` that `recorded` does not cover (by ids; an uncounted one by its description)."""
    known = merge_ranges(r for loss in recorded for r in loss.ranges)
    whats = {loss.what for loss in recorded}
    out = []
    for loss in found:
        covered = all(_contains(known, r) for r in loss.ranges)
        if not covered or (loss.uncounted and loss.what not in whats):
            out.append(loss)
    return out


def load_losses(directory: Path) -> list[Loss]:
    """The losses recorded in `directory` (none if there is no file); ValueError naming the file if bad."""
    path = directory / FILE
    if not path.exists():
        return []
    try:
        doc = json.loads(path.read_text())
        return [Loss(e["kind"], e["what"], tuple((int(a), int(b)) for a, b in e["ranges"]), bool(e["uncounted"]))
                for e in doc["losses"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path} is unreadable ({exc}); move it aside to go on (it lists earlier losses)") \
            from exc


def record_losses(directory: Path, new: Sequence[Loss], how: str) -> None:
    """Add `new` to the directory's record, durably, before anything else is written."""
    if not new:
        return
    path = directory / FILE
    entries = json.loads(path.read_text())["losses"] if path.exists() else []
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    entries += [{"kind": loss.kind, "what": loss.what, "ranges": [list(r) for r in loss.ranges],
                 "count": loss.count, "uncounted": loss.uncounted, "recorded": stamp, "how": how}
                for loss in new]
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w") as fh:
        json.dump({"format": _FORMAT, "losses": entries}, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    fsync_directory(directory)


def quarantined_ids(losses: Sequence[Loss]) -> set[int]:
    """Ids of every quarantined item in a record."""
    return {i for loss in losses if loss.kind == "quarantined" for a, b in loss.ranges for i in range(a, b)}
