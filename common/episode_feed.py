"""Sending recorded transitions to a replay server, with acknowledgements: `romannet mcap feed` and the
learner's offline pre-fill (`romannet learner --offline DIR`) both use this.

    report = feed_files(client, episode_paths(["runs/r1/episodes"]), FeedOptions(), on_progress)

Every /transition message of every file is inserted as it was recorded (the same bytes the actor sent,
so the replay holds them bit for bit) and each insert waits for the server's acknowledgement (written and
fsync'ed). The replay keys inserts by (actor_id, episode_id, step), so feeding the same files again adds
nothing: those come back as duplicates. Up to `window` inserts are in flight at once, which lets the
server's group commit share one fsync among them. A server that does not answer, holds inserts back
(rate limiter) or is shutting down is retried with a pause until `give_up_after_s`; a transition the
server refuses (wrong heightmap size, invalid) is counted as rejected with the reason, and feeding goes on.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from .episode_file import TRANSITION_TOPIC, EpisodeFileError, EpisodeReader
from .errors import RomannetError
from .replay_client import refused_for_good
from .wire_messages import InsertAckMsg
from .zenoh_session import RemoteError

log = logging.getLogger(__name__)

class EncodedInserter(Protocol):
    """What feeding needs of a replay client (ZenohReplayClient has it)."""

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> InsertAckMsg: ...


class FeedError(RomannetError):
    """The replay server could not be reached (or kept refusing) for longer than the feed may wait."""


@dataclass(frozen=True)
class FeedOptions:
    """insert_timeout_s: deadline of one insert request; give_up_after_s: how long one transition is
    retried through outages before the feed stops with FeedError; retry_pause_s: pause between retries;
    window: inserts in flight at once (1 = strictly one after the other, in recorded order)."""

    insert_timeout_s: float = 10.0
    give_up_after_s: float = 120.0
    retry_pause_s: float = 0.5
    window: int = 4

    def __post_init__(self) -> None:
        for name in ("insert_timeout_s", "give_up_after_s", "retry_pause_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} = {getattr(self, name)!r} must be > 0 seconds")
        if not 1 <= self.window <= 64:
            raise ValueError(f"window = {self.window!r} must be 1..64 inserts in flight")


@dataclass
class FeedReport:
    """Totals of a feed; `rejected_reasons` counts refusals by the server's reason."""

    files: int = 0
    transitions: int = 0
    accepted: int = 0
    duplicates: int = 0
    rejected: int = 0
    rejected_reasons: Counter[str] = field(default_factory=Counter)
    truncated_files: list[str] = field(default_factory=list)
    failed_files: dict[str, str] = field(default_factory=dict)  # path -> error (not an episode, ...)
    damaged_files: dict[str, str] = field(default_factory=dict)  # path -> what is damaged (the rest was fed)
    read_bytes: int = 0  # of all files, for progress
    seconds: float = 0.0

    def as_dict(self) -> dict:
        out = dict(self.__dict__)
        out["rejected_reasons"] = dict(self.rejected_reasons)
        out["seconds"] = round(self.seconds, 3)
        return out

    def count(self, ack: InsertAckMsg | None, reason: str = "") -> None:
        self.transitions += 1
        if ack is not None and ack.status == "accepted":
            self.accepted += 1
        elif ack is not None and ack.status == "duplicate":
            self.duplicates += 1
        else:
            self.rejected += 1
            why = reason or (ack.detail if ack is not None else "") or "rejected"
            self.rejected_reasons[why.split(":")[0][:80]] += 1
            if self.rejected <= 5 or self.rejected % 100 == 0:  # not a line per transition of a wrong-size run
                log.warning("the replay server refused a transition (%d so far): %.300s", self.rejected, why)


def insert_with_retry(client: EncodedInserter, data: bytes, opts: FeedOptions,
                      stop: threading.Event | None = None) -> tuple[InsertAckMsg | None, str]:
    """(ack, "") once the server answered; (None, reason) when it refused the bytes for good.

    Raises FeedError after opts.give_up_after_s without an answer (or if `stop` is set meanwhile)."""
    deadline = time.monotonic() + opts.give_up_after_s
    last = ""
    while True:
        try:
            return client.insert_encoded(data, timeout_s=opts.insert_timeout_s), ""
        except RemoteError as err:
            if refused_for_good(err.reason):
                return None, f"{err.reason}: {err.detail}"
            last = str(err)
        except TimeoutError as err:  # NoReplyError: resending is safe, inserts are idempotent
            last = str(err)
        if time.monotonic() + opts.retry_pause_s > deadline or (stop is not None and stop.is_set()):
            raise FeedError(f"the replay server did not accept a transition within {opts.give_up_after_s:g} s: "
                            f"{last}")
        time.sleep(opts.retry_pause_s)


@dataclass(frozen=True)
class FeedProgress:
    """What a progress display needs after each acknowledged transition."""

    path: Path
    file_index: int
    files: int
    done_bytes: int  # of all files, including the current one up to its current message
    total_bytes: int
    report: FeedReport


def transitions_of(reader: EpisodeReader) -> Iterator[tuple[bytes, int]]:
    """(encoded transition, file offset after it) of one episode, in recorded order."""
    for msg in reader.messages({TRANSITION_TOPIC}):
        yield msg.data, msg.end_offset


def feed_stream(client: EncodedInserter, items: Iterable[tuple[bytes, int]], report: FeedReport, opts: FeedOptions,
                on_ack: Callable[[int], None] | None = None, stop: threading.Event | None = None) -> None:
    """Insert every (transition bytes, offset) of `items` with up to opts.window in flight; counts into
    report; on_ack(offset) after each answer. Raises FeedError when the server stays unreachable."""
    with ThreadPoolExecutor(max_workers=opts.window, thread_name_prefix="feed") as pool:
        pending: dict[Future, int] = {}

        def settle(done: set[Future]) -> None:
            for fut in done:
                offset = pending.pop(fut)
                ack, reason = fut.result()  # FeedError propagates
                report.count(ack, reason)
                if on_ack is not None:
                    on_ack(offset)

        try:
            for data, offset in items:
                if stop is not None and stop.is_set():
                    break
                if len(pending) >= opts.window:
                    settle(wait(pending, return_when=FIRST_COMPLETED).done)
                pending[pool.submit(insert_with_retry, client, data, opts, stop)] = offset
            while pending:
                settle(wait(pending, return_when=FIRST_COMPLETED).done)
        except BaseException:
            for fut in pending:
                fut.cancel()
            raise


def _note_health(report: FeedReport, path: Path, reader: EpisodeReader) -> None:
    """A damaged file (fed but for its damaged parts) or one that ends early, in the report and one log line."""
    health = reader.health
    if health is None:  # the feed stopped inside this file
        return
    if health.damaged:
        report.damaged_files[str(path)] = health.describe()
        log.error("%s: %s", path, health.describe())
    elif not health.complete:
        report.truncated_files.append(str(path))
        log.warning("%s: %s", path, health.describe())


def feed_files(client: EncodedInserter, paths: Sequence[Path], opts: FeedOptions | None = None,
               on_progress: Callable[[FeedProgress], None] | None = None,
               stop: threading.Event | None = None) -> FeedReport:
    """Feed every transition of every episode file; a file that is not an episode is recorded in
    report.failed_files (and logged) and the others are fed; of a damaged file every intact chunk is fed
    and the file is recorded in report.damaged_files (and logged, one line naming the damage); a truncated
    one is fed up to its last whole chunk (report.truncated_files). Raises FeedError on a lasting outage."""
    opts = opts or FeedOptions()
    report = FeedReport()
    sizes = [p.stat().st_size if p.is_file() else 0 for p in paths]
    total, before = sum(sizes), 0
    started = time.monotonic()
    for index, (path, size) in enumerate(zip(paths, sizes, strict=True)):
        if stop is not None and stop.is_set():
            break

        def on_ack(offset: int, path: Path = path, index: int = index, before: int = before) -> None:
            if on_progress is not None:
                on_progress(FeedProgress(path, index, len(paths), before + offset, total, report))

        try:
            reader = EpisodeReader(path)
            feed_stream(client, transitions_of(reader), report, opts, on_ack, stop)
        except EpisodeFileError as err:
            report.failed_files[str(path)] = err.problem
            log.error("%s", err)
        else:
            report.files += 1
            _note_health(report, path, reader)
        before += size
        report.read_bytes = before
    report.seconds = time.monotonic() - started
    return report
