"""The replay store's stats: rates over a sliding window and the stats dict (pure functions of the index)."""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import numpy as np

from romannet.common.config_replay import ReplayConfig


class RateMeter:
    """Events per second over the last `window_s` seconds (thread-safe)."""

    def __init__(self, window_s: float = 10.0):
        self.window_s = window_s
        self._events: deque[tuple[float, int]] = deque()
        self._mu = threading.Lock()

    def add(self, n: int) -> None:
        now = time.monotonic()
        with self._mu:
            self._events.append((now, n))
            self._trim(now)

    def _trim(self, now: float) -> None:
        while self._events and self._events[0][0] < now - self.window_s:
            self._events.popleft()

    def rate(self) -> float:
        """Events per second in the window (0 without events)."""
        now = time.monotonic()
        with self._mu:
            self._trim(now)
            if not self._events:
                return 0.0
            span = max(now - self._events[0][0], 1.0)  # a burst shorter than 1 s is not a huge rate
            return sum(n for _, n in self._events) / span


def build_stats(cfg: ReplayConfig, ids: np.ndarray, priorities: np.ndarray, policy_versions: np.ndarray,
                latest_policy: int, counts: dict[str, int], size_bytes: int, inserts_per_s: float,
                samples_per_s: float, per_actor_held: dict[str, int], per_actor_inserts: dict[str, int],
                rejected: dict[str, int], limiter: dict[str, int]) -> dict[str, Any]:
    """The stats dict (JSON-ready: plain numbers, strings, lists and dicts)."""
    size = len(ids)
    if size:
        hist, edges = np.histogram(priorities, bins=cfg.histogram_bins)
        top = np.argsort(-priorities, kind="stable")[:cfg.top_k]
        lag = latest_policy - policy_versions
        policy_lag = {"latest_policy_version": int(latest_policy), "mean": float(lag.mean()),
                      "median": float(np.median(lag)), "max": int(lag.max()),
                      "oldest_policy_version": int(policy_versions.min())}
    else:
        hist, edges, top = np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64)
        policy_lag = {"latest_policy_version": int(latest_policy), "mean": 0.0, "median": 0.0, "max": 0,
                      "oldest_policy_version": None}
    return {
        "size": size,
        "capacity_items": cfg.capacity_items,
        "bytes": int(size_bytes),
        "capacity_bytes": cfg.capacity_bytes,
        "oldest_item_id": int(ids[0]) if size else None,
        "newest_item_id": int(ids[-1]) if size else None,
        "inserts": int(counts.get("inserts", 0)),
        "duplicates": int(counts.get("duplicates", 0)),
        "evicted": int(counts.get("evicted", 0)),
        "samples": int(counts.get("samples", 0)),
        "sample_batches": int(counts.get("sample_batches", 0)),
        "priority_updates": int(counts.get("priority_updates", 0)),
        "priority_updates_ignored": int(counts.get("priority_updates_ignored", 0)),
        "inserts_per_s": float(inserts_per_s),
        "samples_per_s": float(samples_per_s),
        "priority_histogram": {"counts": hist.tolist(), "edges": edges.tolist()},
        "top_priorities": [{"item_id": int(ids[i]), "priority": float(priorities[i])} for i in top],
        "per_actor": {a: {"held": int(per_actor_held.get(a, 0)), "inserted": int(n)}
                      for a, n in sorted(per_actor_inserts.items())},
        "policy_lag": policy_lag,
        "rejected": {k: int(v) for k, v in sorted(rejected.items())},
        "rate_limiter": limiter,
    }
