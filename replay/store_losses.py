"""What the replay store has lost, in one place: the loss check when it opens a directory (refuse an
acknowledged item recovery cannot get back unless the loss is accepted, then record it in losses.json) and
the items found damaged while it runs (quarantined: logged, recorded in losses.json, never offered again).

Apart from replay/store.py so the store keeps to its index and its API; the log lines are the store's
(same logger), so what an operator reads does not depend on this split.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

from .log import is_legacy_segment, list_segments, segment_number
from .losses import Loss, ReplayLossError, describe, load_losses, quarantined_ids, record_losses, unaccepted
from .recovery import Recovered, log_summary, repair, scan_directory

log = logging.getLogger(__name__.rsplit(".", 1)[0] + ".store")  # the store's lines


class LossBook:
    """The items a store does not offer: lost (accepted at a recovery), quarantined before this start
    (recorded in losses.json) and quarantined while it runs."""

    def __init__(self, directory: Path, recorded: list[Loss]):
        self.directory = directory
        self.lost_items = sum(loss.count for loss in recorded if loss.kind == "lost")
        self.recorded_quarantine = quarantined_ids(recorded)
        self._mu = threading.Lock()  # losses.json writes
        self._quarantined: dict[int, str] = {}  # found damaged while this store ran: id -> why

    def record_quarantine(self, found: dict[int, str]) -> None:
        """Log and record items found damaged (losses.json), so no restart offers them again."""
        with self._mu:
            fresh = {i: why for i, why in found.items() if i not in self._quarantined}
            self._quarantined.update(fresh)
            losses = [Loss("quarantined", why, ((i, i + 1),)) for i, why in sorted(fresh.items())]
            for loss in losses:
                log.error("replay item %d quarantined, never sampled again: %s", loss.ranges[0][0], loss.what)
            try:
                record_losses(self.directory, losses, "quarantined when read")
            except OSError as exc:
                log.error("could not record quarantined item(s) in losses.json: %s", exc)

    def quarantined(self) -> list[int]:
        """Every quarantined item id, recorded before or found since, sorted."""
        with self._mu:
            return sorted(self.recorded_quarantine | set(self._quarantined))


def recover(directory: Path, accept_loss: bool) -> tuple[Recovered, LossBook, set[int]]:
    """Scan; refuse (or record, if accepted) a loss not recorded before; repair; drop quarantined items.
    Returns what was recovered, the losses so far and the numbers of the legacy (unchecked) segments."""
    rec = scan_directory(directory)
    recorded = load_losses(directory)
    new = unaccepted(rec.losses, recorded)
    if new and not accept_loss:
        raise ReplayLossError(
            f"replay directory {directory} cannot recover {loss_summary(new)}; restore the damaged "
            "files if you can, or start with --accept-loss to go on without those items (they are then "
            "recorded in losses.json)")
    for loss in new:
        log.error("replay directory %s: lost %s; accepted, recorded in losses.json", directory, describe(loss))
    record_losses(directory, new, "accepted at start (--accept-loss)")
    repair(directory, rec)
    log_summary(rec)
    recorded += new
    book = LossBook(directory, recorded)
    if book.recorded_quarantine:  # a restart from a snapshot taken before they were found
        quarantined, split = book.recorded_quarantine, len(rec.items) - rec.tail_items
        head = [it for it in rec.items[:split] if it[0] not in quarantined]
        tail = [it for it in rec.items[split:] if it[0] not in quarantined]
        rec.items, rec.tail_items = head + tail, len(tail)
    legacy = {segment_number(p) for p in list_segments(directory) if is_legacy_segment(p)}
    return rec, book, legacy


def loss_summary(losses: list[Loss]) -> str:
    """'N acknowledged item(s): <loss>; <loss>' in one line."""
    total = sum(loss.count for loss in losses)
    uncounted = any(loss.uncounted for loss in losses)
    head = f"{total} acknowledged item(s){' or more' if uncounted else ''}" if total else \
        "an uncounted number of acknowledged items"
    return f"{head}: " + "; ".join(describe(loss) for loss in losses)
