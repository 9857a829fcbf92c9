"""The learner's side of weights distribution: publish each version once, serve it on query, publish rates.

    publisher = WeightsPublisher(session, run_id, wire_dtype="bf16")   # declares the fetch queryable
    publisher.publish_weights(version, tensors)       # encode once, put the Weights, announce (version, sha256, size)
    publisher.publish_exploration(version, 0.31, "lae")
    publisher.close()                                 # before the session closes

Only the learner publishes, and versions strictly increase (a smaller or equal version raises ValueError:
actors ignore it anyway, so it can only be a bug). Each version is encoded once (wire_dtype: see
common/weights_wire.py) and put once on `.../weights/data`: Zenoh delivers it to every subscribed actor, and
through a router the learner's link carries one copy whatever the number of actors. The small announcement
follows on the same link, so an actor that got the announcement without the data (it joined mid-way, or
was cut off) fetches the newest with a query `.../weights/fetch?version=N`, answered with the kept bytes
whatever N is (the message carries its own version). An actor that starts after the learner fetches the
same way. Queries are answered on a worker thread, because sending megabytes with CongestionControl.BLOCK
inside a Zenoh callback would stall every other message of the session.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import queue
import threading
from collections.abc import Mapping
from typing import Any

import torch
import zenoh

from romannet.common import wire
from romannet.common.keys import RunKeys
from romannet.common.weights_wire import to_wire
from romannet.common.weightscodec import make_weights
from romannet.common.wire_messages import ExplorationRateMsg, WeightsAnnouncementMsg
from romannet.common.zenoh_session import format_error

log = logging.getLogger(__name__)

_MAX_PENDING_QUERIES = 64  # more waiting fetches than this are refused at once ("overloaded")


class WeightsPublisher:
    """Serves versioned weights and exploration rates of run_id through `session` (the caller's)."""

    def __init__(self, session: zenoh.Session, run_id: str, wire_dtype: str = "fp32", push: bool = True):
        """wire_dtype: "fp32" or "bf16" (common/weights_wire.py). push=False only announces, so every actor
        fetches its own copy (the protocol before the put; kept for the benchmark's comparison)."""
        to_wire({}, wire_dtype)  # a bad dtype fails here, not at the first publish
        self.keys = RunKeys(run_id)
        self.wire_dtype, self.push = wire_dtype, push
        self._session = session
        self._lock = threading.Lock()
        self._encoded: bytes | None = None  # the encoded Weights message of the current version
        self._announcement: WeightsAnnouncementMsg | None = None
        self._rate_version = -1
        self.served = 0  # fetch queries answered with weights
        self.pushed = 0  # versions put on weights/data
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
        weights, announcement = make_weights(version, to_wire(tensors, self.wire_dtype))
        announcement = dataclasses.replace(announcement, pushed=self.push)
        encoded = wire.encode_weights(weights)
        with self._lock:
            self._encoded, self._announcement = encoded, announcement
        if self.push:
            self._session.put(self.keys.weights_data, encoded, congestion_control=zenoh.CongestionControl.BLOCK)
            self.pushed += 1
        # Announce after the bytes are in place, so an actor that reacts at once finds them; on the same
        # link and priority it arrives after the data, so an actor that has the data does not fetch.
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
