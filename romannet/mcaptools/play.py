"""`romannet mcap play FILE`: an episode played back in recorded order and time to Foxglove and/or Zenoh.

With --foxglove the server keeps serving after the last message until Ctrl-C (the app shows what arrived
only while it is connected); Zenoh-only playback ends with the episode.

The file is scanned once for its channels (so every channel is advertised before the first message, and
a truncated file is reported up front), then played: each message is sent when its recorded log time,
divided by --speed, has passed since the first message (--speed 0: no waiting). A pause longer than
--max-gap seconds in the recording (an actor that waited for a replay server) is shortened to it.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

from romannet.common.episode_file import EpisodeReader
from romannet.common.errors import RomannetError
from romannet.common.signals import stop_on_signals
from romannet.common.zenoh_session import make_config, open_session

from .bar import ProgressBar
from .sinks import FoxgloveSink, Sink, ZenohSink

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlayOptions:
    """speed: playback rate (1 = recorded time, 0 = as fast as the sinks take it); max_gap_s: longest
    pause kept from the recording, seconds; loop: play again from the start until stopped."""

    speed: float = 1.0
    max_gap_s: float = 5.0
    loop: bool = False

    def __post_init__(self) -> None:
        if not (self.speed >= 0 and self.speed < float("inf")):
            raise RomannetError(f"--speed {self.speed}: use a rate >= 0 (1 = recorded time, 0 = no waiting)")
        if not self.max_gap_s > 0:
            raise RomannetError(f"--max-gap {self.max_gap_s}: use a positive number of seconds")


def delay_s(previous_ns: int | None, t_ns: int, opts: PlayOptions) -> float:
    """Seconds between sending the previous message (recorded at previous_ns) and this one (t_ns): the
    recorded gap / speed, the gap capped at max_gap_s, never negative; 0 at speed 0 or for the first."""
    if opts.speed == 0 or previous_ns is None:
        return 0.0
    return min(max((t_ns - previous_ns) / 1e9, 0.0), opts.max_gap_s) / opts.speed


def play(path: str, sinks: list[Sink], opts: PlayOptions, stop: threading.Event, total: int = 0) -> int:
    """Send every message of the episode at `path` to each sink; returns the number of messages sent."""
    sent = 0
    with ProgressBar("play", "messages") as bar:
        while True:
            start, target_s, previous, first = time.monotonic(), 0.0, None, None
            for msg in EpisodeReader(path).messages():
                target_s += delay_s(previous, msg.log_time_ns, opts)
                previous = msg.log_time_ns
                first = msg.log_time_ns if first is None else first
                wait_s = start + target_s - time.monotonic()
                if (wait_s > 0 and stop.wait(wait_s)) or stop.is_set():
                    return sent
                for sink in sinks:
                    sink.send(msg)
                sent += 1
                done = (sent - 1) % max(total, 1) + 1
                bar.update(done / max(total, 1), f"{done}/{total} messages, recorded t = "
                           f"{(msg.log_time_ns - first) / 1e9:.1f} s", count=sent)
            if not opts.loop:
                return sent


def scan(path: str) -> tuple[EpisodeReader, int]:
    """Read the file once for its channels, health and message count (EpisodeFileError if no episode)."""
    reader = EpisodeReader(path)
    count = sum(1 for _ in reader.messages())
    return reader, count


@contextlib.contextmanager
def _sinks(args: argparse.Namespace, reader: EpisodeReader, stop: threading.Event) -> Iterator[list[Sink]]:
    channels = list(reader.channels.values())
    with contextlib.ExitStack() as stack:
        sinks: list[Sink] = []
        if args.zenoh:
            session = stack.enter_context(open_session(make_config(
                args.zenoh_config, listen=args.listen or None, connect=args.connect or None)))
            run_id = args.run_id or reader.episode.get("run_id") or "default"
            actor_id = args.actor_id or reader.episode.get("actor_id") or "replay"
            zsink = ZenohSink(session, run_id, actor_id, channels)
            stack.callback(zsink.close)
            log.info("publishing on Zenoh under %s/...", zsink.key_prefix)
            if not zsink.wait_for_subscribers(args.zenoh_wait, stop):
                log.info("no Zenoh subscriber matched within %g s: playing anyway", args.zenoh_wait)
            sinks.append(zsink)
        if args.foxglove is not None:
            fsink = FoxgloveSink(channels, args.foxglove, host=args.foxglove_host)
            stack.callback(fsink.close)
            log.info("Foxglove WebSocket server on ws://%s:%d (protocols foxglove.sdk.v1 and "
                     "foxglove.websocket.v1): open it in the Foxglove app (Open connection -> Foxglove WebSocket), "
                     "or %s", args.foxglove_host, fsink.port, fsink.app_url())
            if args.wait_client != 0:
                timeout = None if args.wait_client < 0 else args.wait_client
                log.info("waiting for a Foxglove client to subscribe%s (Ctrl-C to stop)",
                         "" if timeout is None else f" (at most {timeout:g} s)")
                if not fsink.wait_for_client(timeout, stop):
                    log.info("no Foxglove client subscribed: playing anyway")
            sinks.append(fsink)
        yield sinks


def run_play(args: argparse.Namespace) -> int:
    """`romannet mcap play`; exit code 0 when the whole episode was played."""
    if not args.zenoh and args.foxglove is None:
        raise RomannetError("nothing to play to: pass --foxglove PORT and/or --zenoh")
    opts = PlayOptions(speed=args.speed, max_gap_s=args.max_gap, loop=args.loop)
    reader, total = scan(args.file)
    assert reader.health is not None
    if not reader.health.complete or reader.health.damaged:
        log.warning("%s: %s", args.file, reader.health.describe())
    stop = threading.Event()
    with stop_on_signals(stop, "stopping the playback"), _sinks(args, reader, stop) as sinks:
        started = time.monotonic()
        sent = 0 if stop.is_set() else play(args.file, sinks, opts, stop, total)
        if args.foxglove is not None and not stop.is_set():
            # The app keeps its panels and lets a person scrub what arrived only while the connection lives.
            log.info("played all %d messages; still serving Foxglove on port %d until Ctrl-C", sent,
                     next(s.port for s in sinks if isinstance(s, FoxgloveSink)))
            stop.wait()
    sys.stdout.write(f"played {sent} of {total} messages of {args.file} in {time.monotonic() - started:.1f} s"
                     f"{' (stopped)' if stop.is_set() else ''}\n")
    return 0 if sent >= total or opts.loop else 1
