"""Helpers for the replay tests: small stores, transitions with distinct keys, a simulated kill -9."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from _wire_samples import transition

from romannet.common.config_replay import ReplayConfig
from romannet.common.wire import TransitionMsg
from romannet.replay.store import ReplayStore


def cfg(**overrides: Any) -> ReplayConfig:
    """A small config; fsync stays on (the durability tests rely on it), snapshots only when asked; no ratio
    limit and batches up to 256 (the store tests insert and sample as they please) unless a test sets them."""
    base: dict[str, Any] = dict(capacity_items=1000, min_size_to_sample=1, snapshot_every_s=0.0,
                                snapshot_every_inserts=0, samples_per_insert=0.0, max_batch_size=256)
    base.update(overrides)
    return ReplayConfig(**base)


def tr(step: int, episode: str = "ep-1", actor: str = "sim-0", priority: float | None = None,
       size: int = 8, seed: int = 0, **kw: Any) -> TransitionMsg:
    """A small valid transition with key (actor, episode, step)."""
    return transition(size, size, seed=seed, actor_id=actor, episode_id=episode, step=step,
                      initial_priority=priority, done=False, done_reason="", **kw)


def crash(store: ReplayStore) -> None:
    """Leave the store as kill -9 would: no final snapshot, no segment trailer, nothing more written."""
    store._closed = True
    store._limiter.close()
    store._wake.set()
    store._snapshotter.join()
    log = store._log
    if log._fd is not None:
        os.close(log._fd)
        log._fd = None
    for fd in log._readers.values():
        os.close(fd)
    log._readers.clear()
    store._dir_lock.release()  # the kernel drops a dead process's flock


def segments(directory: Path) -> list[Path]:
    return sorted(Path(directory).glob("segment-*.mcap"))
