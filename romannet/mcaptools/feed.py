"""`romannet mcap feed FILE|DIR ...`: recorded transitions into a running replay server, acknowledged.

The run id (which replay server: `romannet/@v1/<run>/replay/...`) is --run-id, else the run the files
were recorded in (they must agree). Feeding is idempotent (see common/episode_feed.py): a second feed of
the same files reports every transition as a duplicate and adds nothing.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
from pathlib import Path

from romannet.common.episode_feed import FeedOptions, FeedProgress, FeedReport, feed_files
from romannet.common.episode_file import EpisodeFileError, EpisodeReader, episode_paths
from romannet.common.errors import RomannetError
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.signals import stop_on_signals
from romannet.common.zenoh_session import make_config, open_session

from .bar import ProgressBar

log = logging.getLogger(__name__)


def recorded_run_id(path: Path) -> str | None:
    """The run id in an episode file's metadata (read up to its first message), None if unreadable."""
    try:
        reader = EpisodeReader(path)
        messages = reader.messages()
        next(messages, None)
        messages.close()
    except EpisodeFileError:
        return None
    return reader.episode.get("run_id") or None


def resolve_run_id(run_id: str | None, paths: list[Path]) -> str:
    """--run-id, else the one run every readable file was recorded in."""
    if run_id:
        return run_id
    runs = {r for r in map(recorded_run_id, paths) if r}
    if len(runs) != 1:
        found = ", ".join(sorted(runs)) or "none readable"
        raise RomannetError(f"cannot tell which replay server to feed (runs recorded in the files: {found}): "
                            "pass --run-id RUN")
    return runs.pop()


def _detail(p: FeedProgress) -> str:
    r = p.report
    return (f"file {p.file_index + 1}/{p.files} | {r.transitions} transitions: {r.accepted} new, "
            f"{r.duplicates} duplicate, {r.rejected} rejected")


def format_report(report: FeedReport, run_id: str, replay_size: int | None) -> str:
    text = (f"fed {report.files} file(s) to run {run_id}: {report.transitions} transitions, {report.accepted} "
            f"new, {report.duplicates} duplicate(s), {report.rejected} rejected in {report.seconds:.1f} s")
    if report.truncated_files:
        text += f"; {len(report.truncated_files)} truncated file(s) fed up to their last whole chunk"
    if report.rejected_reasons:
        text += f"; rejected: {dict(report.rejected_reasons)}"
    if report.damaged_files:
        text += f"; {len(report.damaged_files)} damaged file(s) fed but for their damaged parts"
    if report.failed_files:
        text += f"; {len(report.failed_files)} file(s) skipped (not episodes)"
    if replay_size is not None:
        text += f"; the replay server now holds {replay_size}"
    return text


def run_feed(args: argparse.Namespace) -> int:
    """`romannet mcap feed`; exit code 0 when every transition was accepted or a duplicate, 1 when one was
    rejected or a file was skipped (not an episode) or damaged (its intact chunks fed), each named on stderr."""
    paths = episode_paths(args.inputs)
    run_id = resolve_run_id(args.run_id, paths)
    opts = FeedOptions(insert_timeout_s=args.timeout, give_up_after_s=args.give_up_after, window=args.window)
    stop = threading.Event()
    with stop_on_signals(stop, "stopping after the inserts in flight"), \
            open_session(make_config(args.zenoh_config, listen=args.listen or None,
                                     connect=args.connect or None)) as session:
        client = ZenohReplayClient(session, run_id)
        if not client.wait_until_ready(args.wait):
            raise RomannetError(f"no replay server for run {run_id!r} answered within {args.wait:g} s (is "
                                "`romannet replay` running, and do --connect and --run-id match it?)")
        log.info("feeding %d file(s) to the replay server of run %s", len(paths), run_id)
        with ProgressBar("feed", "transitions") as bar:
            report = feed_files(client, paths, opts, stop=stop, on_progress=lambda p: bar.update(
                p.done_bytes / max(p.total_bytes, 1), _detail(p), count=p.report.transitions))
        try:
            replay_size: int | None = int(client.stats(timeout_s=5.0)["size"])
        except (TimeoutError, RomannetError, KeyError, ValueError):
            replay_size = None
    for path, problem in {**report.failed_files, **report.damaged_files}.items():
        sys.stderr.write(f"romannet mcap feed: error: {path}: {problem}\n")
    if args.json:
        sys.stdout.write(json.dumps({"run_id": run_id, "replay_size": replay_size, **report.as_dict()}) + "\n")
    else:
        sys.stdout.write(format_report(report, run_id, replay_size) + "\n")
    return 0 if not (report.rejected or report.failed_files or report.damaged_files or stop.is_set()) else 1
