"""The replay server: a ReplayStore served over Zenoh (keys in common/keys.py).

Threads: Zenoh calls our callbacks on its own threads, and a callback that blocks (an fsync, a sample
waiting for the rate limiter) stalls every other message of the session. So callbacks only check the
payload's size and enqueue; three small worker pools do the work:
- insert workers: validate the transition (its PNGs decoded in full), `store.insert` (durable), reply
  with the ack;
- sample workers: `store.sample_encoded` (may wait for the rate limiter), reply with the batch. A pool
  of their own, because a sample waiting for inserts must never occupy the thread an insert needs
  (deadlock);
- one control worker: priority updates and stats, in arrival order.
A full queue is answered at once with an "overloaded" error instead of queueing without bound: at most
max_pending messages and max_queued_bytes bytes wait. A message larger than its kind allows is refused in
the callback, before it is queued or copied (Zenoh's own cap, common/zenoh_limits.py, drops far larger
ones before they reach us).

Bad input never crashes the server: it gets an error reply `<reason>: <detail>`, a log line (throttled)
and a count in stats["server"]["rejected"][kind][reason].
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import zenoh

from romannet.common import wire
from romannet.common.errors import DecodeError
from romannet.common.keys import RunKeys
from romannet.common.wire_messages import InsertAckMsg, PriorityUpdateMsg, TransitionMsg
from romannet.common.zenoh_limits import PRIORITY_UPDATE_BYTES
from romannet.common.zenoh_session import format_error, open_zenoh

from .rejections import Rejections, classify_decode_error
from .validate import check_transition

log = logging.getLogger(__name__)


class Store(Protocol):
    """What the server needs of replay/store.py's ReplayStore."""

    def insert(self, msg: TransitionMsg, encoded: bytes | None = None,
               timeout_s: float = 10.0) -> InsertAckMsg: ...
    def sample_encoded(self, batch_size: int, timeout_s: float = 10.0, rng: Any = None,
                       request_id: str = "local") -> bytes | bytearray: ...
    def update_priorities(self, update: PriorityUpdateMsg) -> int: ...
    def record_rejection(self, reason: str) -> None: ...
    def stats(self) -> dict: ...


@dataclasses.dataclass(frozen=True)
class ServerLimits:
    """Knobs of the transport layer (the buffer's own settings are in ReplayConfig).

    max_insert_bytes: larger transition payloads are refused before decoding (a 224x224 RGB-D
    transition is ~0.3 MB). expected_shape: (h, w) in pixels every heightmap must have. max_wait_s: cap on
    the rate-limiter wait (seconds) a client asks for with the query parameter wait_ms, on insert and
    sample alike; without the parameter the wait is default_wait_s.
    """

    insert_workers: int = 16  # many: they mostly wait for fsync, and concurrent inserts share one
    sample_workers: int = 2
    max_pending: int = 256
    max_insert_bytes: int = 16 * 1024 * 1024
    # Bytes of queued messages: a message that would pass it is answered "overloaded" (clients resend)
    # unless nothing is queued, so one large valid transition is always taken. Bounds memory under a flood.
    max_queued_bytes: int = 64 * 1024 * 1024
    # Any other message (priority updates, sample and stats requests); common/wire.py reads 4 MiB at most.
    max_control_bytes: int = PRIORITY_UPDATE_BYTES
    default_wait_s: float = 5.0
    max_wait_s: float = 60.0
    expected_shape: tuple[int, int] | None = None
    # Decode every PNG in full at insert (replay/validate.py); False checks headers and CRCs only
    # (`romannet replay --skip-pixel-decode`, for the benchmark's comparison).
    decode_pixels: bool = True


def _payload(obj: Any) -> bytes:
    payload = getattr(obj, "payload", None)
    return payload.to_bytes() if payload is not None else b""


def _payload_size(obj: Any) -> int:
    payload = getattr(obj, "payload", None)
    return len(payload) if payload is not None else 0  # ZBytes' length: nothing is copied


def _json_default(obj: Any) -> Any:
    # store.stats() may hold numpy scalars or arrays; JSON has only Python numbers and lists.
    for attr in ("tolist", "item"):
        if hasattr(obj, attr):
            return getattr(obj, attr)()
    return str(obj)


class ReplayServer:
    """Serves `store` on the replay keys of run_id through `session` (which the caller owns and closes).

    start() declares everything; stop() undeclares (no new queries), finishes queued work within
    drain_timeout_s, and returns. Use as a context manager.
    """

    def __init__(self, store: Store, session: zenoh.Session, run_id: str, limits: ServerLimits | None = None):
        self.store = store
        self.keys = RunKeys(run_id)
        self.limits = limits or ServerLimits()
        self._session = session
        self.rejections = Rejections()
        self._handled: dict[str, int] = {"insert": 0, "sample": 0, "priorities": 0, "stats": 0}
        self._count_lock = threading.Lock()
        self._queues = {name: queue.Queue(maxsize=self.limits.max_pending)
                        for name in ("insert", "sample", "control")}
        self._queued_bytes = 0  # payload bytes of every queued message, under _count_lock
        self._threads: list[threading.Thread] = []
        self._declared: list[Any] = []
        self._started_s = time.monotonic()

    # ------------------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start the workers, declare queryables and subscriber, then the liveliness token (last, so a
        client that sees the token finds everything served)."""
        pools = (("insert", self.limits.insert_workers), ("sample", self.limits.sample_workers),
                 ("control", 1))
        for name, count in pools:
            for i in range(count):
                t = threading.Thread(target=self._work, args=(self._queues[name],),
                                     name=f"replay-{name}-{i}", daemon=True)
                t.start()
                self._threads.append(t)
        s = self._session
        self._declared = [
            s.declare_queryable(self.keys.replay_inserts, self._enqueue("insert", self._handle_insert)),
            s.declare_queryable(self.keys.replay_sample, self._enqueue("sample", self._handle_sample)),
            s.declare_queryable(self.keys.replay_stats, self._enqueue("control", self._handle_stats)),
            s.declare_subscriber(self.keys.replay_priorities,
                                 self._enqueue("control", self._handle_priorities)),
            s.liveliness().declare_token(self.keys.replay_alive),
        ]
        log.info("replay server serving %s/replay/*", self.keys.root)

    def stop(self, drain_timeout_s: float = 10.0) -> None:
        """Stop taking messages, then let the workers finish what is queued (at most drain_timeout_s)."""
        for entity in reversed(self._declared):  # token first: clients stop choosing this server
            try:
                entity.undeclare()
            except Exception as exc:  # an already-closed session: nothing left to undeclare
                log.debug("undeclare failed: %s", exc)
        self._declared = []
        for name, q in self._queues.items():
            for _ in range(sum(1 for t in self._threads if t.name.startswith(f"replay-{name}-"))):
                q.put(None)  # one stop marker per worker, behind the queued work
        deadline = time.monotonic() + drain_timeout_s
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        alive = [t.name for t in self._threads if t.is_alive()]
        if alive:
            log.warning("workers still busy after %.1f s: %s", drain_timeout_s, alive)
        self._threads = []
        # A callback already running when we undeclared may have queued behind the stop markers: answer
        # those queries now, or their clients would wait out their whole timeout.
        for q in self._queues.values():
            while True:
                try:
                    item = q.get_nowait()
                except queue.Empty:
                    break
                if item is not None and isinstance(item[1], zenoh.Query):
                    with contextlib.suppress(Exception):
                        item[1].reply_err(format_error("shutting_down", "the replay server is stopping"))
                    item[1].drop()

    def __enter__(self) -> ReplayServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --------------------------------------------------------------------------------- dispatching
    def _enqueue(self, kind: str, handler: Callable[[Any], None]) -> Callable[[Any], None]:
        """A Zenoh callback that checks the message's size, queues it for `kind` and returns at once."""
        q = self._queues[kind]
        max_bytes = self.limits.max_insert_bytes if kind == "insert" else self.limits.max_control_bytes

        def callback(obj: Any) -> None:
            size = _payload_size(obj)
            if size > max_bytes:
                what = "transition" if kind == "insert" else "message"
                self._refuse(obj, "oversized", f"{what} is {size} bytes; this server accepts at most {max_bytes}")
                return
            with self._count_lock:
                over = self._queued_bytes > 0 and self._queued_bytes + size > self.limits.max_queued_bytes
                if not over:
                    self._queued_bytes += size
            if over:
                self._refuse(obj, "overloaded", f"{self.limits.max_queued_bytes} bytes of requests already "
                             "queued; retry later", kind=kind)
                return
            try:
                q.put_nowait((handler, obj, size))
            except queue.Full:
                self._release(size)
                self._refuse(obj, "overloaded", f"{q.maxsize} {kind} requests already queued; retry later",
                             kind=kind)
        return callback

    def _refuse(self, obj: Any, reason: str, detail: str, kind: str | None = None) -> None:
        """Reject a message in the callback (never queued) and finalise it if it is a query."""
        self._reject(obj, reason, detail, kind=kind)
        if isinstance(obj, zenoh.Query):
            obj.drop()

    def _release(self, size: int) -> None:
        with self._count_lock:
            self._queued_bytes -= size

    def _work(self, q: queue.Queue) -> None:
        while True:
            item = q.get()
            if item is None:
                return
            handler, obj, size = item
            try:
                handler(obj)
            except Exception as exc:  # a bug in a handler must not kill the worker: answer and go on
                log.exception("replay handler failed")
                self._reject(obj, "internal", f"{type(exc).__name__}: {exc}")
            finally:
                self._release(size)
                if isinstance(obj, zenoh.Query):
                    obj.drop()  # finalises the query, so the client's get ends without waiting its timeout

    def _reject(self, obj: Any, reason: str, detail: str, kind: str | None = None) -> None:
        """Count and log a refused message; answer it with an error reply if it is a query."""
        kind = kind or self._kind_of(obj)
        self.rejections.record(kind, reason, detail)
        try:
            self.store.record_rejection(f"{kind}/{reason}")  # persisted with the store's counters
        except Exception as exc:  # a closed store at shutdown: the server's own count remains
            log.debug("store.record_rejection failed: %s", exc)
        if isinstance(obj, zenoh.Query):
            try:
                obj.reply_err(format_error(reason, detail[:1000]))
            except Exception as exc:  # already answered or dropped: the count and log are what is left
                log.debug("could not send the error reply: %s", exc)

    def _kind_of(self, obj: Any) -> str:
        key = str(obj.key_expr)
        if not key.startswith(self.keys.root):
            return "unknown"
        chunks = key.split("/")
        return "insert" if chunks[-2:-1] == ["insert"] else chunks[-1]  # .../replay/insert/<actor_id>

    def _count(self, kind: str) -> None:
        with self._count_lock:
            self._handled[kind] += 1

    # ------------------------------------------------------------------------------------ handlers
    def _handle_insert(self, query: zenoh.Query) -> None:
        data = _payload(query)  # its size was checked in the callback (_enqueue)
        try:
            msg = check_transition(data, self.limits.expected_shape, self.limits.max_insert_bytes,
                                   self.limits.decode_pixels)
        except DecodeError as err:
            self._reject(query, classify_decode_error(str(err)), str(err))
            return
        key_actor = str(query.key_expr).rsplit("/", 1)[-1]
        if msg.actor_id != key_actor:
            # The key is what a secure router's access control checked; the payload must agree with it, or
            # an actor could insert under another's id through its own key.
            self._reject(query, "wrong_actor", f"transition of actor {msg.actor_id!r} sent on the insert key "
                         f"of {key_actor!r}")
            return
        try:
            ack = self.store.insert(msg, encoded=data, timeout_s=self._wait_s(query))
        except TimeoutError as err:
            # The samples-per-insert limiter holds inserts back (the learner lags): not bad input.
            query.reply_err(format_error("rate_limited", str(err) or "the rate limiter holds inserts"))
            return
        except ValueError as err:  # the store's own checks (e.g. a transition larger than the capacity)
            self._reject(query, "store_refused", str(err))
            return
        if ack.status == "rejected":
            self.rejections.record("insert", "store_rejected", ack.detail)
        self._count("insert")
        query.reply(query.key_expr, wire.encode_insert_ack(ack))

    def _handle_sample(self, query: zenoh.Query) -> None:
        try:
            request = wire.decode_sample_request(_payload(query))
        except DecodeError as err:
            self._reject(query, classify_decode_error(str(err)), str(err))
            return
        wait_s = self._wait_s(query)
        try:
            reply = self.store.sample_encoded(request.batch_size, timeout_s=wait_s,
                                              request_id=request.request_id)
        except TimeoutError as err:
            # Not counted as a rejection: waiting for data is normal flow, not bad input.
            query.reply_err(format_error("rate_limited", str(err) or f"no batch within {wait_s:.3g} s"))
            return
        except ValueError as err:
            self._reject(query, "store_refused", str(err))
            return
        self._count("sample")
        query.reply(self.keys.replay_sample, reply)

    def _wait_s(self, query: zenoh.Query) -> float:
        """The rate-limiter wait the client asked for (wait_ms), within [0, max_wait_s] seconds."""
        try:
            wait_s = float(query.parameters.get("wait_ms")) / 1000.0
        except (TypeError, ValueError):
            return self.limits.default_wait_s
        return min(max(wait_s, 0.0), self.limits.max_wait_s) if wait_s == wait_s else 0.0

    def _handle_priorities(self, sample: zenoh.Sample) -> None:
        try:
            update = wire.decode_priority_update(_payload(sample))
        except DecodeError as err:
            reason = classify_decode_error(str(err))
            self.rejections.record("priorities", reason, str(err))
            self.store.record_rejection(f"priorities/{reason}")
            return
        self.store.update_priorities(update)
        self._count("priorities")

    def _handle_stats(self, query: zenoh.Query) -> None:
        self._count("stats")
        query.reply(self.keys.replay_stats, json.dumps(self.stats(), default=_json_default).encode())

    def stats(self) -> dict:
        """The store's stats plus this server's: {"server": {"handled", "rejected", "queued", "uptime_s"}}."""
        out = dict(self.store.stats())
        with self._count_lock:
            handled = dict(self._handled)
        out["server"] = {
            "handled": handled,
            "rejected": self.rejections.snapshot(),
            "rejected_total": self.rejections.total(),
            "queued": {name: q.qsize() for name, q in self._queues.items()},
            "queued_bytes": self._queued_bytes,
            "uptime_s": round(time.monotonic() - self._started_s, 3),
        }
        return out


def run_replay_server(cfg: Any, directory: str | Path, zenoh_config: zenoh.Config, stop_event: threading.Event,
                      run_id: str = "default", limits: ServerLimits | None = None,
                      ready: Callable[[ReplayServer], None] | None = None, accept_loss: bool = False) -> dict:
    """Open the store in `directory`, serve it until stop_event is set, then shut down cleanly.

    cfg: the ReplayConfig. The store is opened first: it locks the directory, so a second server on a
    directory in use raises DirectoryInUseError before it opens a Zenoh session or announces anything.
    Snapshots every cfg.snapshot_interval_s seconds (if the config has it) and once more at shutdown.
    Shutdown order matters: stop taking queries (so nothing new is acknowledged), finish queued work,
    snapshot, close the store (flushes the log), close the session. Returns the final stats.
    ready(server) is called once the server is serving (tests and `romannet up` use it).
    """
    from .store import ReplayStore

    interval_s = float(getattr(cfg, "snapshot_interval_s", 0) or 0)
    final: dict = {}
    store = ReplayStore(cfg, directory, accept_loss)  # takes the directory's lock; may refuse a loss
    try:
        session = open_zenoh(zenoh_config)  # a port in use: one ZenohOpenError line
    except BaseException:
        store.close()
        raise
    try:
        try:
            server = ReplayServer(store, session, run_id, limits)
            server.start()
            try:
                if ready is not None:
                    ready(server)
                next_snapshot_s = time.monotonic() + interval_s
                # Short waits, not one long one, so a signal handler that sets the event is seen promptly.
                while not stop_event.wait(0.2):
                    if interval_s > 0 and time.monotonic() >= next_snapshot_s:
                        store.snapshot()
                        next_snapshot_s = time.monotonic() + interval_s
            finally:
                log.info("replay server stopping: no new queries; finishing queued work")
                server.stop()
                final = server.stats()
                store.snapshot()
        finally:
            store.close()
    finally:
        session.close()  # last: an unclosed session would keep the interpreter from exiting
    log.info("replay server stopped: %s items, %s rejected", final.get("size"),
             final.get("server", {}).get("rejected_total"))
    return final
