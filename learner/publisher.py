"""The learner's side of weights distribution: announce each version, serve it on query, publish rates.

    publisher = WeightsPublisher(session, run_id)     # declares the fetch queryable
    publisher.publish_weights(version, tensors)       # encode once, keep, announce (version, sha256, size)
    publisher.publish_exploration(version, 0.31, "lae")
    publisher.close()                                 # before the session closes

Only the learner publishes, and versions strictly increase (a smaller or equal version raises ValueError:
actors ignore it anyway, so it can only be a bug). The Weights bytes are encoded once per version and kept;
a query `.../weights/fetch?version=N` is answered with them whatever N is (N is the current version, or an
older one the actor was late for, or absent: the latest is what the actor wants in every case; the
message carries its own version). Queries are answered on a worker thread, because sending megabytes with
CongestionControl.BLOCK inside a Zenoh callback would stall every other message of the session.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from collections.abc import Mapping
from typing import Any

import torch
import zenoh

from romannet.common import wire
from romannet.common.keys import RunKeys
from romannet.common.weightscodec import make_weights
from romannet.common.wire_messages import ExplorationRateMsg, WeightsAnnouncementMsg
from romannet.common.zenoh_session import format_error

log = logging.getLogger(__name__)

_MAX_PENDING_QUERIES = 64  # more waiting fetches than this are refused at once ("overloaded")


class WeightsPublisher:
    """Serves versioned weights and exploration rates of run_id through `session` (the caller's)."""

    def __init__(self, session: zenoh.Session, run_id: str):
        self.keys = RunKeys(run_id)
        self._session = session
        self._lock = threading.Lock()
        self._encoded: bytes | None = None  # the encoded Weights message of the current version
        self._announcement: WeightsAnnouncementMsg | None = None
        self._rate_version = -1
        self.served = 0  # fetch queries answered with weights
        self._queries: queue.Queue = queue.Queue(maxsize=_MAX_PENDING_QUERIES)
        self._worker = threading.Thread(target=self._serve, name="weights-serve", daemon=True)
        self._worker.start()
        self._declared: list[Any] = [session.declare_queryable(self.keys.weights_fetch, self._on_query)]

    @property
    def version(self) -> int | None:
        """The current weights version, or None before the first publish."""
        with self._lock:
            return self._announcement.version if self._announcement else None

    def publish_weights(self, version: int, tensors: Mapping[str, torch.Tensor]) -> WeightsAnnouncementMsg:
        """Make `version` current and announce it. Raises ValueError if version does not increase or a
        tensor is not finite (a diverged learner must not ship NaN weights to the fleet)."""
        current = self.version
        if current is not None and version <= current:
            raise ValueError(f"weights version {version} is not newer than the published {current}: "
                             "versions must strictly increase")
        weights, announcement = make_weights(version, tensors)
        encoded = wire.encode_weights(weights)
        with self._lock:
            self._encoded, self._announcement = encoded, announcement
        # Announce after the bytes are in place, so an actor that reacts at once finds them.
        self._session.put(self.keys.weights_announce, wire.encode_weights_announcement(announcement),
                          congestion_control=zenoh.CongestionControl.BLOCK)
        log.debug("published weights v%d (%d bytes)", version, announcement.size_bytes)
        return announcement

    def publish_exploration(self, version: int, value: float, policy: str) -> ExplorationRateMsg:
        """Publish the exploration rate computed at `version` (the update count); versions strictly
        increase. Raises ValueError on a stale version or a value outside [0, 1]."""
        if version <= self._rate_version:
            raise ValueError(f"exploration version {version} is not newer than the published "
                             f"{self._rate_version}: versions must strictly increase")
        msg = ExplorationRateMsg(version, float(value), policy)
        self._session.put(self.keys.exploration, wire.encode_exploration_rate(msg),
                          congestion_control=zenoh.CongestionControl.BLOCK)
        self._rate_version = version
        return msg

    def close(self) -> None:
        """Undeclare the queryable, answer what is queued, stop the worker. Idempotent."""
        for entity in self._declared:
            with contextlib.suppress(Exception):  # the session may already be closed
                entity.undeclare()
        self._declared = []
        if self._worker.is_alive():
            self._queries.put(None)
            self._worker.join(10.0)

    def __enter__(self) -> WeightsPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------------- serving
    def _on_query(self, query: zenoh.Query) -> None:
        try:
            self._queries.put_nowait(query)
        except queue.Full:
            with contextlib.suppress(Exception):
                query.reply_err(format_error("overloaded", f"{_MAX_PENDING_QUERIES} weight fetches queued"))
            query.drop()

    def _serve(self) -> None:
        while True:
            query = self._queries.get()
            if query is None:
                return
            try:
                with self._lock:
                    encoded = self._encoded
                if encoded is None:
                    query.reply_err(format_error("no_weights", "the learner has not published weights yet"))
                else:
                    # The reply inherits the query's congestion control (query_one asks for BLOCK);
                    # zenoh 1.x ignores a congestion_control argument here.
                    query.reply(self.keys.weights_fetch, encoded)
                    self.served += 1
            except Exception as exc:  # the actor went away mid-reply: nothing to do but note it
                log.warning("weights fetch reply failed: %s", exc)
            finally:
                query.drop()  # finalises the query, so the actor's get ends without waiting its timeout
