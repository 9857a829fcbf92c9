"""`romannet replay --check DIR`: read every held item of a replay directory and check it, writing nothing.

Recovery at start reads only the log after the newest snapshot, so damage in a snapshotted segment
shows only when the item is sampled (the store then quarantines it). This check finds it beforehand: it
scans like recovery does (no repair, no snapshot .tmp cleanup, so it is safe beside a running server),
then reads each held record and checks it against its own checksum. It reports each damaged item, each
loss recovery would refuse, and the losses recorded earlier; the exit code is 1 when anything is found
that losses.json does not already list, else 0.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

from .log import is_legacy_segment, list_segments, segment_number, segment_path
from .losses import Loss, describe, format_ranges, load_losses, quarantined_ids, to_ranges, unaccepted
from .recordcheck import record_problem
from .recovery import scan_directory

log = logging.getLogger(__name__)


@dataclass
class CheckReport:
    """What a check found."""

    held: int = 0  # items recovery would hold
    checked: int = 0  # of those, records checked against their checksum
    unchecked: int = 0  # records of legacy segments (written before records had checksums)
    damaged: dict[int, str] = field(default_factory=dict)  # item id -> why
    unaccepted: list[Loss] = field(default_factory=list)  # losses recovery would refuse to go on over
    recorded: list[Loss] = field(default_factory=list)  # losses.json

    @property
    def ok(self) -> bool:
        return not self.damaged and not self.unaccepted


def check_directory(directory: Path) -> CheckReport:
    """Check every item a replay store in `directory` would hold; writes nothing."""
    report = CheckReport()
    report.recorded = load_losses(directory)
    rec = scan_directory(directory, clean=False)
    report.unaccepted = unaccepted(rec.losses, report.recorded)
    quarantined = quarantined_ids(report.recorded)
    legacy = {segment_number(p) for p in list_segments(directory) if is_legacy_segment(p)}
    fds: dict[int, int] = {}
    try:
        for item_id, loc, _ in rec.items:
            if item_id in quarantined:
                continue
            report.held += 1
            if loc.segment in legacy:
                report.unchecked += 1
                continue
            try:
                fd = fds.get(loc.segment)
                if fd is None:
                    fd = fds[loc.segment] = os.open(segment_path(directory, loc.segment), os.O_RDONLY)
                data = os.pread(fd, loc.length, loc.data_offset)
                problem = record_problem(item_id, data) if len(data) == loc.length else \
                    f"item {item_id}: only {len(data)} of {loc.length} bytes on disk"
            except OSError as exc:
                problem = f"item {item_id}: unreadable ({exc})"
            report.checked += 1
            if problem:
                report.damaged[item_id] = f"{problem} in segment-{loc.segment:06d}.mcap at offset {loc.data_offset}"
    finally:
        for fd in fds.values():
            os.close(fd)
    return report


def log_report(directory: Path, report: CheckReport) -> None:
    """One line per finding and a summary line."""
    for why in list(report.damaged.values())[:20]:
        log.error("damaged: %s", why)
    if len(report.damaged) > 20:
        log.error("damaged: %d more item(s)", len(report.damaged) - 20)
    for loss in report.unaccepted:
        log.error("lost: %s", describe(loss))
    for loss in report.recorded:
        log.info("recorded earlier in losses.json (%s): %s", loss.kind, describe(loss))
    summary = (f"replay --check {directory}: {report.held} item(s) held, {report.checked} checked"
               f"{f', {report.unchecked} unchecked (legacy segments without record checksums)' if report.unchecked else ''}"
               f", {len(report.damaged)} damaged"
               f"{f' (ids {format_ranges(to_ranges(report.damaged))})' if report.damaged else ''}"
               f", {sum(loss.count for loss in report.unaccepted)} acknowledged item(s) lost and not accepted")
    (log.info if report.ok else log.error)("%s", summary)
    if not report.ok:
        log.error("the server quarantines damaged items when it reads them; a loss needs "
                  "`romannet replay --dir %s --accept-loss` (or restoring the damaged files)", directory)


def run_check(directory: Path) -> int:
    """Exit code of `romannet replay --check DIR`: 0 if nothing new is wrong, 1 otherwise, 2 if no such directory."""
    if not directory.is_dir() or not list_segments(directory) and not list(directory.glob("snapshot-*.npz")):
        log.error("replay --check %s: not a replay directory (no segment-*.mcap or snapshot-*.npz files)", directory)
        return 2
    report = check_directory(directory)
    log_report(directory, report)
    return 0 if report.ok else 1
