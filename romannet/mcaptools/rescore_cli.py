"""`romannet mcap rescore` on the command line: settings from the flags, files one by one, a progress bar,
optional feeding of the rescored transitions, and a summary (text or --json)."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
import threading
from pathlib import Path

from romannet.common.episode_feed import FeedOptions, FeedReport, feed_stream
from romannet.common.episode_file import EpisodeFileError, episode_paths
from romannet.common.errors import RomannetError
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.signals import stop_on_signals
from romannet.common.zenoh_session import make_config, open_session

from .bar import ProgressBar
from .feed import resolve_run_id
from .rescore import FileResult, RescoreSettings, load_reward_table, rescore_file, touches_kernel
from .rescoring import SuccessRule

log = logging.getLogger(__name__)


def settings_of(args: argparse.Namespace) -> RescoreSettings:
    table = load_reward_table(args.reward_config) if args.reward_config else {}
    rule = SuccessRule(args.success, args.changed_height, args.push_area, args.pick_area)
    return RescoreSettings(table, tuple(args.overrides), rule)


def format_result(r: FileResult) -> str:
    where = r.output or "(not written)"
    return (f"{r.source} -> {where}: {r.steps} steps, X changed on {r.success_changed}, reward changed on "
            f"{r.reward_changed}; reward sum {r.reward_sum_recorded:.3f} -> {r.reward_sum:.3f}"
            + (" (source truncated or damaged: read but for those parts)" if r.truncated else ""))


def run_rescore(args: argparse.Namespace) -> int:
    """Exit code 0 when every file was rescored (and, with --feed, every transition accepted or a duplicate)."""
    if args.out is None and not args.feed:
        raise RomannetError("nothing to do: pass --out DIR and/or --feed")
    settings = settings_of(args)
    paths = episode_paths(args.inputs)
    if touches_kernel(settings):
        log.info("TPG kernel fields shape the learner's labels, not the recorded R_tp: they go into the new "
                 "files' config; the learner uses its own [reward] when it trains")
    out_dir = Path(args.out) if args.out else None
    results: list[FileResult] = []
    errors: list[str] = []
    report = FeedReport()
    stop = threading.Event()
    with stop_on_signals(stop, "stopping after the current file"), contextlib.ExitStack() as stack:
        client = None
        if args.feed:
            run_id = resolve_run_id(args.run_id, paths)
            session = stack.enter_context(open_session(make_config(
                args.zenoh_config, listen=args.listen or None, connect=args.connect or None)))
            client = ZenohReplayClient(session, run_id)
            if not client.wait_until_ready(args.wait):
                raise RomannetError(f"no replay server for run {run_id!r} answered within {args.wait:g} s")
        opts = FeedOptions(insert_timeout_s=args.timeout, give_up_after_s=args.give_up_after, window=args.window)
        with ProgressBar("rescore", "files") as bar:
            for index, path in enumerate(paths):
                if stop.is_set():
                    break
                try:
                    result = rescore_file(path, settings, out_dir)
                except EpisodeFileError as err:
                    errors.append(str(err))
                    sys.stderr.write(f"romannet mcap rescore: error: {err}\n")
                    continue
                if client is not None:
                    feed_stream(client, ((data, 0) for data in result.transitions), report, opts, stop=stop)
                results.append(result)
                bar.update((index + 1) / len(paths), f"{index + 1}/{len(paths)} files, {report.accepted} fed",
                           count=index + 1)
    if args.json:
        sys.stdout.write(json.dumps({"files": [r.as_dict() for r in results], "errors": errors,
                                     "feed": report.as_dict() if args.feed else None}) + "\n")
    else:
        for r in results:
            sys.stdout.write(format_result(r) + "\n")
        if args.feed:
            sys.stdout.write(f"fed {report.transitions} rescored transitions: {report.accepted} new, "
                             f"{report.duplicates} duplicate(s), {report.rejected} rejected\n")
    return 1 if errors or report.rejected or stop.is_set() else 0
