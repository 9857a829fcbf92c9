"""The sender thread: drains the spool to the replay server, oldest first, with backoff while unreachable.

Outcomes of one insert (the item is the spool's oldest; it is resent until one of the first two happens):

* ack "accepted" or "duplicate" -> the item is acknowledged: removed from the spool. A duplicate is what a
  resend of a transition the server already stored gets (its ack was lost, or the actor restarted).
* ack "rejected", or an error reply that resending cannot cure (common/replay_client.INSERT_REFUSALS:
  undecodable, oversized, wrong shape, ...) -> the item moves to the spool's rejected/ folder with the
  reason and is logged; it is never resent.
* "rate_limited" (RateLimitedError): the server is up, and its samples-per-insert limiter held the insert
  back for the whole wait because the learner lags: pacing, not an outage. The same item is resent 50 ms later
  (the server itself did the waiting); the server stays reachable; one INFO line the first time only.
* no reply (NoReplyError), any other error reply (shutting_down, overloaded, internal, unknown) or any other
  exception -> the
  server is treated as unreachable: wait (exponential backoff, resend_backoff_initial_s doubling up to
  resend_backoff_max_s) and resend the same item. One log line per outage, one when acks flow again.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

from romannet.common import romannet_pb2 as pb
from romannet.common.errors import DecodeError
from romannet.common.interfaces import ReplayClient
from romannet.common.replay_client import refused_for_good
from romannet.common.zenoh_session import RemoteError

from .spool import Spool

log = logging.getLogger(__name__)

# The error reply of a server that holds inserts back because the learner lags (see the module docstring).
PACING_REASON = "rate_limited"
# Pause after a pacing reply before the resend: the server held the insert for its wait already, so only a
# reply that came back at once (a server configured with no wait) needs this to avoid a tight loop.
_PACED_RESEND_S = 0.05


@dataclass
class SenderStats:
    """Counters of one sender (since the process started)."""

    sent: int = 0  # insert requests made, resends included
    acked: int = 0  # transitions acknowledged (accepted + duplicates): stored on the server
    accepted: int = 0
    duplicates: int = 0
    rejected: int = 0  # moved to rejected/, never resent
    failures: int = 0  # requests that got no usable answer (resent later)
    reachable: bool = True  # False from the first failure until the server next answers (an ack or a pacing reply)
    paced: int = 0  # inserts the server's rate limiter held back (the learner lags), resent 50 ms later
    pacing: bool = False  # True from a pacing reply until the next failure (acks in between keep it)
    last_error: str = ""


def item_key(data: bytes) -> tuple[str, str, int] | None:
    """(actor_id, episode_id, step) of an encoded transition, without decoding its PNGs; None if unreadable."""
    try:
        t = pb.Transition.FromString(data)
    except Exception:  # protobuf raises its own DecodeError; a corrupt item is judged by the server
        return None
    return t.actor_id, t.episode_id, t.step


def spool_pause(stats: SenderStats, full: str) -> tuple[str, str]:
    """(kind, reason) of an actor's wait on a full spool (`full` says how full), judged from its sender:

    * "outage": the last request got no usable answer (the server down, unreachable, failing): news.
    * "paced": the server's rate limiter has held inserts back since the last failure (the learner lags
      behind the fleet): routine on a CPU learner.
    * "waiting": the server answered the last request and the next one is in flight (held by the rate
      limiter before its first pacing reply, or just slow); it turns into one of the others when it ends.
    """
    if not stats.reachable:
        return "outage", f"{full}; is the replay server reachable? last send error: {stats.last_error or 'none'}"
    if stats.pacing:
        return "paced", f"paced by the learner (the replay server's samples_per_insert limit); {full}"
    return "waiting", f"waiting for the replay server to acknowledge; {full}"


class Sender:
    """Background thread sending `spool` items, encoded transitions, through `client.insert_encoded`."""

    def __init__(self, spool: Spool, client: ReplayClient, insert_timeout_s: float = 10.0,
                 backoff_initial_s: float = 0.5, backoff_max_s: float = 10.0):
        self.spool, self.client = spool, client
        self.insert_timeout_s = float(insert_timeout_s)
        self.backoff_initial_s, self.backoff_max_s = float(backoff_initial_s), float(backoff_max_s)
        self._lock = threading.Lock()
        self._stats = SenderStats()
        self._stop = threading.Event()
        self._flush_deadline = float("inf")  # monotonic s; after stop(): give up on what is left then
        self._thread = threading.Thread(target=self._run, name="spool-sender", daemon=True)
        self._down_since: float | None = None
        self._told_pacing = False

    def start(self) -> Sender:
        self._thread.start()
        return self

    def stats(self) -> SenderStats:
        """A copy of the counters."""
        with self._lock:
            return SenderStats(**vars(self._stats))

    def stop(self, flush_s: float = 0.0) -> bool:
        """Keep sending for up to flush_s seconds until the spool is empty, then end the thread.

        Returns True if the spool is empty; what is left stays on disk and is sent by the next start.
        """
        self._flush_deadline = time.monotonic() + max(0.0, flush_s)
        self._stop.set()
        if self._thread.is_alive():
            # An insert under way ends by its own timeout.
            self._thread.join(max(0.0, flush_s) + self.insert_timeout_s + 1.0)
        left = self.spool.items
        if left:
            log.warning("spool: %d transition(s) (%d bytes) not acknowledged; kept in %s for the next start",
                        left, self.spool.bytes, self.spool.dir)
        return left == 0

    # -------------------------------------------------------------------------------------- thread
    def _done(self) -> bool:
        return self._stop.is_set() and (self.spool.items == 0 or time.monotonic() >= self._flush_deadline)

    def _run(self) -> None:
        backoff_s = self.backoff_initial_s
        while not self._done():
            seq = self.spool.wait_for_item(0.2)
            if seq is None:
                continue
            outcome = self._send(seq)
            if outcome != "failed":  # the server answered
                backoff_s = self.backoff_initial_s
            if outcome == "settled":
                continue
            wait_s = _PACED_RESEND_S if outcome == "paced" else backoff_s
            if self._stop.is_set():
                wait_s = min(wait_s, max(0.0, self._flush_deadline - time.monotonic()))
            # Wake early on stop() only to re-check the deadline; sleeping past it would delay the exit.
            end = time.monotonic() + wait_s
            while not self._done() and time.monotonic() < end:
                time.sleep(min(0.05, max(0.0, end - time.monotonic())))
            if outcome == "failed":
                backoff_s = min(backoff_s * 2.0, self.backoff_max_s)

    def _send(self, seq: int) -> str:
        """One attempt for item seq: "settled" (acknowledged or rejected), "paced" (the server's rate limiter
        held it back: resend soon) or "failed" (resend after a backoff)."""
        try:
            data = self.spool.read(seq)
        except FileNotFoundError:  # removed behind our back (an operator cleaning up): nothing to send
            self.spool.remove(seq)
            return "settled"
        key = item_key(data)
        key_text = "/".join(map(str, key)) if key else f"spool item {seq}"
        with self._lock:
            self._stats.sent += 1
        try:
            ack = self.client.insert_encoded(data, timeout_s=self.insert_timeout_s)
        except DecodeError as err:  # only the in-process path decodes here: the bytes are corrupt
            self._reject(seq, key_text, f"undecodable: {err}")
            return "settled"
        except RemoteError as err:
            if err.reason == PACING_REASON:
                self._paced(err.detail)
                return "paced"
            if refused_for_good(err.reason):
                self._reject(seq, key_text, f"{err.reason}: {err.detail}")
                return "settled"
            self._failure(f"{err.reason}: {err.detail}")
            return "failed"
        except Exception as err:  # TimeoutError (no reply), a closing session, ...: resend later
            self._failure(f"{type(err).__name__}: {err}")
            return "failed"
        if key is not None and (ack.actor_id, ack.episode_id, ack.step) != key:
            self._failure(f"ack for {ack.actor_id}/{ack.episode_id}/{ack.step} while sending {key_text}")
            return "failed"
        if ack.status == "rejected":
            self._reject(seq, key_text, f"rejected: {ack.detail}")
            return "settled"
        self.spool.remove(seq)
        with self._lock:
            self._stats.acked += 1
            self._stats.accepted += ack.status == "accepted"
            self._stats.duplicates += ack.status == "duplicate"
        self._answered()
        return "settled"

    def _answered(self) -> None:
        """The server answered (an ack or a pacing reply): an outage, if one was on, is over."""
        with self._lock:
            was_down = not self._stats.reachable
            self._stats.reachable = True
        if was_down:
            down_s = time.monotonic() - (self._down_since or time.monotonic())
            log.info("replay server reachable again after %.1f s; %d transition(s) pending in the spool",
                     down_s, self.spool.items)
            self._down_since = None

    def _paced(self, detail: str) -> None:
        with self._lock:
            self._stats.paced += 1
            self._stats.pacing = True
        self._answered()
        if not self._told_pacing:
            self._told_pacing = True
            log.info("the replay server paces this actor to the learner: its rate limiter holds inserts back "
                     "while the learner lags (samples_per_insert); the actor waits, which is normal when the "
                     "learner is slower than the fleet (%s)", detail[:300])
        else:
            log.debug("insert held back by the rate limiter (%s)", detail[:300])

    def _failure(self, why: str) -> None:
        with self._lock:
            self._stats.failures += 1
            self._stats.last_error = why[:500]
            self._stats.pacing = False
            first = self._stats.reachable
            self._stats.reachable = False
        if first:
            self._down_since = time.monotonic()
            log.warning("replay server unreachable (%s); the actor keeps acting and spools transitions "
                        "(%d pending, %d bytes; it pauses at %d items / %d bytes) and resends with backoff",
                        why[:300], self.spool.items, self.spool.bytes, self.spool.max_items, self.spool.max_bytes)

    def _reject(self, seq: int, key_text: str, reason: str) -> None:
        path = self.spool.reject(seq, reason, key_text)
        with self._lock:
            self._stats.rejected += 1
        log.error("replay server refused transition %s (%s); moved to %s and not resent",
                  key_text, reason[:300], path)
