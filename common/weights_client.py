"""WeightsSource over Zenoh: how an actor learns of new weights and exploration rates from the learner.

Usage (the session is the caller's; close the source before the session):

    with open_session(make_config(connect=["tcp/127.0.0.1:7447"], listen=[])) as session:
        with ZenohWeightsSource(session, run_id="run-1", validate=lambda t: validate_tensors(model, t)) as src:
            ...
            new = src.poll_weights()            # None, or (version, tensors): the newest not yet returned
            rate = src.poll_exploration()       # None, or the newest ExplorationRateMsg not yet returned

Protocol (learner/publisher.py): the learner puts each version's Weights once on `.../weights/data` (a router
fans it out to every actor), then a small WeightsAnnouncement (version, sha256, size) on
`.../weights/announce`. This source takes the pushed Weights; an announced version it did not get that way
(it joined mid-way, or its link was down) it fetches with a query on `.../weights/fetch?version=N` that has
a timeout, checked against the announced SHA-256 and size. An actor that starts after the learner (or sees
the learner restart) missed the last version: the learner's liveliness token appearing triggers a fetch of
the latest. Every Weights is checked (its SHA-256, safetensors without pickle, finite values, and the
caller's validate: names, shapes, dtypes); bf16 tensors are widened to fp32 (common/weights_wire.py).
Decoding runs on a thread of its own, so Zenoh callbacks stay short and poll_*() never wait for the network.

Versions only increase: pushed weights not newer than the ones held are refused, an announcement, fetch
reply or rate not newer than the newest seen is ignored. Bad messages (undecodable, digest or size
mismatch, out of order, weights the actor's model refuses) are logged in one line (throttled) and counted in
`stats()`; nothing raises into the actor, which keeps its weights.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any

import torch
import zenoh

from . import wire
from .errors import DecodeError
from .keys import RunKeys
from .weights_wire import from_wire
from .weightscodec import weights_state_dict
from .wire_messages import ExplorationRateMsg, WeightsAnnouncementMsg, WeightsMsg
from .zenoh_session import ZenohQueryError, query_one

log = logging.getLogger(__name__)

# Seconds between two log lines of the same failure kind: a flood of bad messages must not flood the log.
_LOG_EVERY_S = 5.0
_LATEST = -1  # a pending fetch with no announced version: ask for whatever the learner has
# Seconds an announced version's pushed data may trail its announcement before it is fetched instead.
_PUSH_GRACE_S = 1.0


class ZenohWeightsSource:
    """WeightsSource (common/interfaces.py) fed by the learner of run_id through `session`.

    fetch_timeout_s: deadline of one weights query (seconds; 23 MB over loopback takes ~0.1 s).
    validate: optional check of decoded tensors (e.g. `lambda t: validate_tensors(model, t)`); whatever
    it raises rejects that version. Call close() (or use `with`) before closing the session.
    """

    def __init__(self, session: zenoh.Session, run_id: str, fetch_timeout_s: float = 10.0,
                 validate: Callable[[Mapping[str, torch.Tensor]], None] | None = None):
        self.keys = RunKeys(run_id)
        self.fetch_timeout_s = float(fetch_timeout_s)
        self._session = session
        self._validate = validate
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._closed = False
        self._counts: Counter[str] = Counter()
        self._last_logged: dict[str, float] = {}
        # Weights: newest version seen in any form (announced or fetched), the pending fetch, the result.
        self._newest_seen = -1
        self._pending: WeightsAnnouncementMsg | int | None = None
        self._pushed: zenoh.ZBytes | None = None  # the newest Weights put by the learner, not yet decoded
        self._ready: tuple[int, dict[str, torch.Tensor]] | None = None
        self._held_sha = ""  # SHA-256 of the newest version taken (ready or returned)
        self._returned_version = -1
        # Exploration: newest received and newest returned.
        self._rate: ExplorationRateMsg | None = None
        self._returned_rate_version = -1
        # Set when the learner's liveliness token goes away: its next appearance is a new incarnation
        # (a restart without a checkpoint, or a resume from an older one) whose versions may be lower.
        self._learner_gone = False
        self._thread = threading.Thread(target=self._fetch_loop, name="weights-fetch", daemon=True)
        self._thread.start()
        self._declared: list[Any] = [
            session.declare_subscriber(self.keys.weights_data, self._on_data),
            session.declare_subscriber(self.keys.weights_announce, self._on_announcement),
            session.declare_subscriber(self.keys.exploration, self._on_exploration),
            # history=True: a learner already alive reports at once, which triggers the first fetch.
            session.liveliness().declare_subscriber(self.keys.learner_alive, self._on_learner_alive,
                                                    history=True),
        ]

    # ------------------------------------------------------------------------------------ interface
    def poll_weights(self) -> tuple[int, dict[str, torch.Tensor]] | None:
        """The newest (version, state tensors) fetched and not yet returned, or None. Never blocks on I/O."""
        with self._lock:
            ready, self._ready = self._ready, None
            if ready is None or ready[0] <= self._returned_version:
                return None
            self._returned_version = ready[0]
            return ready

    def poll_exploration(self) -> ExplorationRateMsg | None:
        """The newest exploration rate received and not yet returned, or None."""
        with self._lock:
            rate = self._rate
            if rate is None or rate.version <= self._returned_rate_version:
                return None
            self._returned_rate_version = rate.version
            return rate

    def stats(self) -> dict[str, int]:
        """Counters: announcements, fetched, rates, ignored_stale, rejected_<reason>, fetch_failed, ..."""
        with self._lock:
            out = dict(self._counts)
            out["newest_version"] = self._newest_seen
            out["returned_version"] = self._returned_version
            return out

    def close(self) -> None:
        """Undeclare the subscribers and stop the fetch thread (a fetch under way ends by its timeout)."""
        for entity in reversed(self._declared):
            try:
                entity.undeclare()
            except Exception as exc:  # a session closed first: nothing left to undeclare
                log.debug("undeclare failed: %s", exc)
        self._declared = []
        with self._lock:
            self._closed = True
            self._wake.notify_all()
        self._thread.join(self.fetch_timeout_s + 1.0)

    def __enter__(self) -> ZenohWeightsSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------------ callbacks
    # Zenoh runs these on its own threads: decode a few bytes, update state under the lock, return.
    def _on_announcement(self, sample: zenoh.Sample) -> None:
        try:
            ann = wire.decode_weights_announcement(sample.payload.to_bytes())
        except DecodeError as err:
            self._reject("bad_announcement", str(err))
            return
        with self._lock:
            self._counts["announcements"] += 1
            if ann.version <= self._newest_seen:
                self._counts["announced_held" if ann.version == self._held_version() else "ignored_stale"] += 1
                return
            self._newest_seen = ann.version
            self._pending = ann  # replaces an older pending one: only the newest is worth fetching
            self._wake.notify_all()

    def _on_data(self, sample: zenoh.Sample) -> None:
        # Decoding megabytes here would stall the session: keep the payload for the fetch thread. A newer
        # one replaces it unseen, as only the newest is worth loading.
        with self._lock:
            self._counts["pushed"] += 1
            if self._pushed is not None:
                self._counts["pushed_superseded"] += 1
            self._pushed = sample.payload
            self._wake.notify_all()

    def _on_exploration(self, sample: zenoh.Sample) -> None:
        try:
            rate = wire.decode_exploration_rate(sample.payload.to_bytes())
        except DecodeError as err:
            self._reject("bad_exploration", str(err))
            return
        with self._lock:
            self._counts["rates"] += 1
            if self._rate is not None and rate.version <= self._rate.version:
                self._counts["ignored_stale_rates"] += 1
                return
            self._rate = rate

    def _on_learner_alive(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            log.info("the learner's liveliness token is gone; keeping weights version %d",
                     self._returned_version)
            with self._lock:
                self._learner_gone = True
                self._counts["learner_gone"] += 1
            return
        with self._lock:
            if self._learner_gone:
                # Versions count the learner's updates; a restarted learner may count from lower. Without
                # this reset the actor would ignore it until it passed the old count.
                log.info("the learner is back: accepting its weights from version 0 again (held v%d)",
                         self._returned_version)
                self._learner_gone = False
                self._newest_seen = self._returned_version = self._returned_rate_version = -1
                self._ready, self._rate, self._held_sha = None, None, ""
                self._counts["learner_restarts"] += 1
            self._pending = _LATEST
            self._wake.notify_all()

    # ------------------------------------------------------------------------------------ fetching
    def _fetch_loop(self) -> None:
        waited_for = -1  # the announced version whose pushed data was last waited for
        while True:
            with self._lock:
                while self._pending is None and self._pushed is None and not self._closed:
                    self._wake.wait()
                if self._closed:
                    return
                # Pushed data first: it usually is the announced version, which then needs no fetch.
                pushed, self._pushed = self._pushed, None
                pending = None
                if pushed is None:
                    pending = self._pending
                    if isinstance(pending, WeightsAnnouncementMsg):
                        if pending.version <= self._held_version():
                            self._pending = None
                            self._counts["announced_held"] += 1  # the push brought it
                            continue
                        if (pending.pushed or self._counts["pushed"]) and waited_for != pending.version:
                            # Zenoh calls each subscriber on its own thread, so the announcement may come
                            # first, even of the first version: give pushed data a moment before fetching.
                            waited_for = pending.version
                            self._wake.wait(_PUSH_GRACE_S)
                            continue
                    self._pending = None
            try:
                if pushed is not None:
                    self._take_pushed(pushed.to_bytes())
                else:
                    self._fetch(pending)
            except Exception as exc:  # a bug here must not end the thread: the actor keeps its weights
                self._reject("internal", f"{type(exc).__name__}: {exc}")

    def _held_version(self) -> int:
        """The newest version taken (ready or returned); call under the lock."""
        return max(self._returned_version, self._ready[0] if self._ready else -1)

    def _take_pushed(self, data: bytes) -> None:
        """Check and take a Weights message the learner put; refuse one that is not newer than ours."""
        try:
            msg = wire.decode_weights(data)  # the size bound, the schema, SHA-256 of the payload
        except DecodeError as err:
            # One line per kind of damage, not per message: a flood of one bad message stays one line.
            self._reject("bad_weights", f"pushed weights ({len(data)} bytes) refused, keeping "
                         f"v{self._returned_version}: {err}", throttle_key=f"bad_weights:pushed:{str(err)[:60]}")
            return
        with self._lock:
            held, gone = self._held_version(), self._learner_gone
            duplicate = msg.version == held and msg.sha256_hex == self._held_sha
        if duplicate or gone:  # a fetch brought it first; or a restarted learner's, taken once it is back
            self._counts["ignored_stale"] += 1
            return
        if msg.version <= held:
            self._reject("out_of_order", f"pushed weights v{msg.version} refused, keeping v{held}: not newer "
                         "(versions only increase)", throttle_key=f"out_of_order:{msg.version}")
            return
        self._take(msg, msg.version, time.monotonic())

    def _fetch(self, pending: WeightsAnnouncementMsg | int) -> None:
        ann = pending if isinstance(pending, WeightsAnnouncementMsg) else None
        parameters = f"version={ann.version}" if ann is not None else ""
        started = time.monotonic()
        try:
            data = query_one(self._session, self.keys.weights_fetch, None, self.fetch_timeout_s, parameters)
        except (ZenohQueryError, TimeoutError) as err:
            self._reject("fetch_failed", f"weights fetch ({parameters or 'latest'}) failed: {err}")
            return
        try:
            msg = wire.decode_weights(data)
            if ann is not None and msg.version == ann.version:
                if msg.sha256_hex != ann.sha256_hex:
                    raise DecodeError(f"weights v{msg.version} have SHA-256 {msg.sha256_hex}, announced "
                                      f"{ann.sha256_hex}")
                if len(msg.safetensors) != ann.size_bytes:
                    raise DecodeError(f"weights v{msg.version} are {len(msg.safetensors)} bytes, announced "
                                      f"{ann.size_bytes}")
            elif ann is not None and msg.version < ann.version:
                # The learner no longer has what it announced (a restart without --resume): not newer.
                raise DecodeError(f"asked for weights v{ann.version}, got the older v{msg.version}")
        except DecodeError as err:
            self._refuse(ann.version if ann is not None else "latest", err)
            return
        self._take(msg, ann.version if ann is not None else "latest", started, "fetched")

    def _take(self, msg: WeightsMsg, asked: int | str, started: float, count: str = "taken_pushed") -> None:
        """Decode, widen and validate msg's tensors; make them the ready version if newer than the held.
        asked: the version the log names if they are refused (what was announced or pushed, or "latest")."""
        try:
            tensors = from_wire(weights_state_dict(msg))
            if self._validate is not None:
                self._validate(tensors)
        except Exception as err:  # DecodeError, or whatever the caller's validate raises
            self._refuse(asked, err)
            return
        with self._lock:
            if msg.version <= self._held_version():
                self._counts["ignored_stale"] += 1
                return
            self._newest_seen = max(self._newest_seen, msg.version)
            self._ready, self._held_sha = (msg.version, tensors), msg.sha256_hex
            self._counts[count] += 1
        log.debug("%s weights v%d (%d bytes) in %.3f s", count, msg.version, len(msg.safetensors),
                  time.monotonic() - started)

    def _refuse(self, version: int | str, err: Exception) -> None:
        # Logged once per version (the throttle key holds it): a refused version is rare and its reason is
        # what an operator needs; the weights in use stay as they are.
        self._reject("bad_weights", f"weights {version} refused, keeping v{self._returned_version}: "
                     f"{type(err).__name__}: {err}", throttle_key=f"bad_weights:{version}")

    def _reject(self, reason: str, detail: str, throttle_key: str | None = None) -> None:
        """Count a bad message or failed fetch and log it, at most once per _LOG_EVERY_S per throttle_key
        (default: the reason)."""
        now = time.monotonic()
        key = throttle_key or reason
        with self._lock:
            self._counts[f"rejected_{reason}"] += 1
            count = self._counts[f"rejected_{reason}"]
            if now - self._last_logged.get(key, -_LOG_EVERY_S) < _LOG_EVERY_S:
                return
            if len(self._last_logged) > 256:  # per-version keys: forget the ones past their throttle window
                self._last_logged = {k: t for k, t in self._last_logged.items() if now - t < _LOG_EVERY_S}
            self._last_logged[key] = now
        log.warning("weights source: %s (%d so far): %s", reason, count, detail[:500])
