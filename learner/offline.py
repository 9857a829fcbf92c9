"""Offline learning: pre-fill the replay server from MCAP episode recordings before training.

`romannet learner --offline DIR` (and `romannet up --from-recordings DIR`) feed every recorded transition
to the replay server this learner trains from, through the same acknowledged, idempotent inserts an
actor uses (common/episode_feed.py), then train as usual. Without actors that is offline training on the
recordings (real-robot episodes, say); with actors attached the buffer holds recorded and live
experience side by side and the learner samples both by priority. A restarted learner feeds the files
again and the replay answers "duplicate" for each: nothing is added twice.

Damaged recordings do not stop it: a file that is not an episode is skipped and of a damaged one every
intact chunk is fed, each named in one log line, and the summary line counts them; the learner then trains
(its exit code is about training, not the recordings; `romannet mcap inspect --verify` checks them).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

from romannet.common.episode_feed import EncodedInserter, FeedOptions, FeedProgress, FeedReport, feed_files
from romannet.common.episode_file import episode_paths
from romannet.common.errors import RomannetError

log = logging.getLogger(__name__)


class _Ready(EncodedInserter, Protocol):
    """A replay client that can also wait for its server (ZenohReplayClient)."""

    def wait_until_ready(self, timeout_s: float = 10.0) -> bool: ...


def prefill(client: _Ready, inputs: Sequence[str | Path], stop: threading.Event, wait_s: float = 120.0,
            opts: FeedOptions | None = None, log_every_s: float = 10.0) -> FeedReport:
    """Feed every episode file named by `inputs` (files or directories); returns the totals.

    Raises RomannetError if the replay server does not appear within wait_s, or refuses every transition
    (recordings of another heightmap size than this run's [workspace])."""
    paths = episode_paths(inputs)
    if not client.wait_until_ready(wait_s):
        raise RomannetError(f"--offline: no replay server answered within {wait_s:g} s")
    log.info("offline: feeding %d recorded episode file(s) to the replay server before training", len(paths))
    next_log = [time.monotonic() + log_every_s]

    def on_progress(p: FeedProgress) -> None:
        if time.monotonic() >= next_log[0]:
            next_log[0] = time.monotonic() + log_every_s
            log.info("offline: %.0f %% (file %d/%d), %d transitions fed (%d new)",
                     100 * p.done_bytes / max(p.total_bytes, 1), p.file_index + 1, p.files, p.report.transitions,
                     p.report.accepted)

    report = feed_files(client, paths, opts or FeedOptions(), on_progress, stop)
    log.info("offline: %d file(s), %d transitions: %d new, %d already in the replay, %d rejected%s, in %.1f s%s",
             report.files, report.transitions, report.accepted, report.duplicates, report.rejected,
             f" ({dict(report.rejected_reasons)})" if report.rejected else "", report.seconds, damage_note(report))
    if report.transitions and not (report.accepted or report.duplicates):
        raise RomannetError(f"--offline: the replay server refused every recorded transition "
                            f"({dict(report.rejected_reasons)}): were they recorded with this run's [workspace] "
                            "(heightmap size)?")
    if not report.transitions and (report.failed_files or report.damaged_files):
        log.error("offline: none of the %d recorded file(s) held a readable transition: nothing to train on from "
                  "them (each is named above)", len(paths))
    return report


def damage_note(report: FeedReport) -> str:
    """'; 2 damaged file(s) fed but for their damaged parts, 1 skipped (not an episode)' or ''. Each such
    file has its own log line (common/episode_feed.py); this is the count for the summary line."""
    parts = []
    if report.damaged_files:
        parts.append(f"{len(report.damaged_files)} damaged file(s) fed but for their damaged parts")
    if report.failed_files:
        parts.append(f"{len(report.failed_files)} skipped (not an episode)")
    if report.truncated_files:
        parts.append(f"{len(report.truncated_files)} truncated, fed up to their last whole chunk")
    return "; " + ", ".join(parts) if parts else ""
