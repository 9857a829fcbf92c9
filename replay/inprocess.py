"""InProcessReplayClient: the common.interfaces.ReplayClient protocol over a ReplayStore in this process
(unit tests, single-process runs). Same semantics as the Zenoh client: durable acks, TimeoutError when
the rate limiter holds a call, evicted ids ignored in priority updates."""

from __future__ import annotations

import dataclasses

from romannet.common.wire import (
    InsertAckMsg,
    PriorityUpdateMsg,
    SampleBatchMsg,
    TransitionMsg,
    decode_transition,
)

from .store import ReplayStore


class InProcessReplayClient:
    """ReplayClient backed directly by `store` (which the caller owns and closes)."""

    def __init__(self, store: ReplayStore):
        self.store = store

    def insert(self, transition: TransitionMsg, timeout_s: float = 10.0) -> InsertAckMsg:
        """Insert; returns after the transition is durable (accepted/duplicate) or rejected."""
        return self.store.insert(transition, timeout_s=timeout_s)

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> InsertAckMsg:
        """insert() of encode_transition bytes: decoded here, as the store takes transitions."""
        return self.insert(decode_transition(data), timeout_s)

    def sample(self, batch_size: int, timeout_s: float = 10.0) -> SampleBatchMsg:
        """A prioritized batch with decoded, validated transitions (as the Zenoh client returns them)."""
        batch = self.store.sample(batch_size, timeout_s=timeout_s)
        items = tuple(dataclasses.replace(it, transition=decode_transition(it.transition))
                      if isinstance(it.transition, bytes) else it for it in batch.items)
        return dataclasses.replace(batch, items=items)

    def update_priorities(self, update: PriorityUpdateMsg) -> None:
        """Set priorities by item id; ids of evicted items are ignored."""
        self.store.update_priorities(update)

    def stats(self, timeout_s: float = 10.0) -> dict:
        """The store's stats dict (timeout_s is unused: nothing to wait for in-process)."""
        return self.store.stats()
