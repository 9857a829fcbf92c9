"""ReplayStore: the durable prioritized replay buffer behind the Zenoh service and the in-process client.

Thread-safe (Zenoh callbacks call it from several threads). An insert returns only after its bytes are in
an fsync'ed MCAP log chunk (log.py; concurrent inserts share one fsync), so every acknowledgement
survives kill -9 and power loss; items become sampleable in id order once durable. The index (priorities,
locations, idempotency keys) lives in memory and is snapshotted periodically by a background thread;
restart = snapshot + log tail (recovery.py). Transition bytes stay on disk and are read per sample (the
OS page cache keeps recent ones in memory), so memory does not grow with capacity_bytes. One store per
directory: it holds <dir>/LOCK (common/dirlock.py) from before recovery until close, so a second store
(another replay server, a tool) on a directory in use fails at once with DirectoryInUseError.

Damage: recovery names every acknowledged item it cannot get back, and the store refuses to open over
such a loss (ReplayLossError, one line with the count and ids) until it is accepted (`accept_loss`),
which records it in <dir>/losses.json first. Every sampled record is checked against its own checksum
(recordcheck.py) as it is read; a damaged one is quarantined: taken out of the index, recorded in
losses.json, counted in stats, and the batch is drawn again without it. The loss check at open and the
quarantine record are store_losses.py's, reading a drawn batch store_reads.py's.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from romannet.common.config_replay import ReplayConfig
from romannet.common.dirlock import DirectoryLock
from romannet.common.wire import (
    InsertAckMsg,
    PriorityUpdateMsg,
    SampleBatchMsg,
    SampleItem,
    TransitionMsg,
    encode_transition,
)

from .log import Location, SegmentLog
from .prioritized import RankBasedSampler, annealed_beta, is_weights
from .ratelimiter import RateLimiter
from .recordcheck import record_problem
from .recovery import ItemMeta, Key, priority_suffix
from .snapshot import index_arrays, write_snapshot
from .store_losses import recover
from .store_reads import Drawn, read_batch, read_batch_encoded
from .storestats import RateMeter, build_stats

log = logging.getLogger(__name__)

_T = TypeVar("_T")


class _Inflight:
    """An insert of one key between admission and durability; resends of the key wait for it."""

    def __init__(self) -> None:
        self.done = threading.Event()
        self.item_id: int | None = None


class ReplayStore:
    """Durable prioritized replay in `directory` (created if missing; recovered if it holds data).

    accept_loss: go on even if recovery finds acknowledged items it cannot get back (they are recorded
    in losses.json first); without it such a loss raises ReplayLossError and nothing is written."""

    def __init__(self, cfg: ReplayConfig, directory: str | Path, accept_loss: bool = False):
        self.cfg = cfg
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()  # the index below
        self._snapshot_lock = threading.Lock()  # one snapshot at a time
        cap = cfg.capacity_items
        self._sampler = RankBasedSampler(cap, cfg.alpha)
        self._loc = np.zeros((cap, 5), dtype=np.int64)  # Location fields per slot
        self._pv = np.zeros(cap, dtype=np.int64)  # policy version per slot
        self._keys: list[Key | None] = [None] * cap
        self._by_key: dict[Key, int] = {}
        self._inflight: dict[Key, _Inflight] = {}
        self._pending_meta: dict[int, ItemMeta] = {}  # appended, not yet durable
        self._lo = 0  # no item below this id is held (eviction watermark)
        self._next_id = 0  # next id to assign
        self._bytes = 0
        self._last_loc: Location | None = None  # of the newest durable item: where a recovery scan starts
        self._per_actor_held: Counter[str] = Counter()
        self._c: Counter[str] = Counter()  # inserts, duplicates, samples, sample_batches, ...
        self._per_actor_inserts: Counter[str] = Counter()
        self._rejected: Counter[str] = Counter()
        self._latest_policy = 0
        self._insert_rate, self._sample_rate = RateMeter(), RateMeter()
        self._rng = np.random.default_rng()
        self._closed = False
        self._limiter = RateLimiter(cfg.min_size_to_sample, cfg.spi_limit, cfg.spi_tolerance)
        self._dir_lock = DirectoryLock(self.directory, "replay directory")  # before recovery repairs anything
        try:
            self.recovered, self._losses, self._legacy_segments = recover(self.directory, accept_loss)
            self._load(self.recovered)
            self._log = SegmentLog(self.directory, cfg.segment_max_bytes, cfg.fsync)
        except BaseException:
            self._dir_lock.release()
            raise
        self._since_snapshot = 0
        self._wake = threading.Event()
        self._snapshotter = threading.Thread(target=self._snapshot_loop, name="replay-snapshot", daemon=True)
        self._snapshotter.start()

    # ------------------------------------------------------------------------------------------ recovery
    def _load(self, rec: Any) -> None:
        c = rec.counters
        self._c.update(c.get("counts", {}))
        self._per_actor_inserts.update(c.get("per_actor_inserts", {}))
        self._rejected.update(c.get("rejected", {}))
        self._latest_policy = int(c.get("latest_policy", 0))
        self._next_id = rec.next_item_id
        if rec.items:
            self._lo = rec.items[0][0]
        for item_id, loc, meta in rec.items:
            self._add(item_id, loc, meta)
        for _, _, meta in rec.items[len(rec.items) - rec.tail_items:]:  # logged after the snapshot
            self._c["inserts"] += 1
            self._per_actor_inserts[meta.key[0]] += 1
        limiter = c.get("limiter", {})
        self._limiter.restore(int(limiter.get("inserts", 0)) + rec.tail_items, int(limiter.get("samples", 0)),
                              len(self._sampler))

    # ---------------------------------------------------------------------------------------- index ops
    def _evict_for(self, length: int) -> None:
        """Drop the oldest items until one more item of `length` bytes fits. Caller holds the lock."""
        cfg = self.cfg
        while len(self._sampler) and (len(self._sampler) + 1 > cfg.capacity_items
                                      or self._bytes + length > cfg.capacity_bytes):
            item_id = self._lo
            self._lo += 1
            if not self._sampler.remove(item_id):
                continue  # a gap left by a dropped log chunk
            slot = item_id % cfg.capacity_items
            key = self._keys[slot]
            assert key is not None
            self._keys[slot] = None
            del self._by_key[key]
            self._per_actor_held[key[0]] -= 1
            self._bytes -= int(self._loc[slot, 4])
            self._c["evicted"] += 1

    def _add(self, item_id: int, loc: Location, meta: ItemMeta) -> None:
        """Make a durable item sampleable. Caller holds the lock."""
        self._evict_for(loc.length)
        if not len(self._sampler):
            self._lo = item_id
        slot = item_id % self.cfg.capacity_items
        self._sampler.add(item_id, meta.priority)
        self._loc[slot] = (loc.segment, loc.chunk_offset, loc.chunk_first_id, loc.data_offset, loc.length)
        self._pv[slot] = meta.policy_version
        self._keys[slot] = meta.key
        self._by_key[meta.key] = item_id
        self._per_actor_held[meta.key[0]] += 1
        self._bytes += loc.length
        self._latest_policy = max(self._latest_policy, meta.policy_version)
        self._last_loc = loc

    def _publish(self) -> None:
        """Add every record the log made durable, in id order. Caller holds the lock."""
        for item_id, loc in self._log.pop_durable():
            meta = self._pending_meta.pop(item_id)
            self._add(item_id, loc, meta)
            self._c["inserts"] += 1
            self._per_actor_inserts[meta.key[0]] += 1
            self._since_snapshot += 1
        self._limiter.set_size(len(self._sampler))

    def _location(self, item_id: int) -> Location:
        return Location(*(int(v) for v in self._loc[item_id % self.cfg.capacity_items]))

    # -------------------------------------------------------------------------------------------- API
    def insert(self, msg: TransitionMsg, encoded: bytes | None = None, timeout_s: float = 10.0) -> InsertAckMsg:
        """Store a transition durably; idempotent on (actor_id, episode_id, step).

        `encoded` (encode_transition(msg), e.g. as received) saves re-encoding. Returns 'accepted' or
        'duplicate' (with the original item id) once the item is fsync'ed, or 'rejected' with a reason.
        Raises TimeoutError if the rate limiter holds the insert for timeout_s seconds.
        """
        key: Key = (msg.actor_id, msg.episode_id, msg.step)
        ack = dict(actor_id=msg.actor_id, episode_id=msg.episode_id, step=msg.step)
        deadline = time.monotonic() + timeout_s
        data = encoded if encoded is not None else encode_transition(msg)
        if len(data) > self.cfg.max_item_bytes:
            self.record_rejection("oversized")
            return InsertAckMsg(**ack, status="rejected", detail=f"transition is {len(data)} bytes; the "
                                f"replay server accepts at most {self.cfg.max_item_bytes} (max_item_bytes)")
        while True:
            with self._lock:
                if self._closed:
                    raise RuntimeError("replay store is closed")
                if key in self._by_key:
                    self._c["duplicates"] += 1
                    return InsertAckMsg(**ack, status="duplicate", item_id=self._by_key[key])
                other = self._inflight.get(key)
                if other is None:
                    mine = self._inflight[key] = _Inflight()
                    break
            if not other.done.wait(max(0.0, deadline - time.monotonic())):  # a resend racing its original
                raise TimeoutError(f"the first insert of {key} did not finish within {timeout_s:g} s")
        try:
            mine.item_id = self._insert_new(key, msg, data, deadline)
        finally:
            with self._lock:
                del self._inflight[key]
            mine.done.set()
        if self._since_snapshot >= self.cfg.snapshot_every_inserts > 0:
            self._wake.set()
        return InsertAckMsg(**ack, status="accepted", item_id=mine.item_id)

    def _insert_new(self, key: Key, msg: TransitionMsg, data: bytes, deadline: float) -> int:
        self._limiter.acquire_insert(max(0.0, deadline - time.monotonic()))
        try:
            with self._lock:
                item_id = self._next_id
                priority = (msg.initial_priority if msg.initial_priority is not None
                            else self._sampler.max_priority(default=1.0))
                ticket = self._log.append(item_id, data, msg.end_ns, priority_suffix(priority))
                self._next_id += 1
                self._pending_meta[item_id] = ItemMeta(key, priority, msg.policy_version)
        except BaseException:
            self._limiter.cancel_insert()
            raise
        self._log.sync(ticket)  # errors here leave the log failed; the store must be reopened
        with self._lock:
            self._publish()
        self._insert_rate.add(1)
        return item_id

    def sample(self, batch_size: int, timeout_s: float = 10.0, rng: np.random.Generator | None = None,
               request_id: str = "local") -> SampleBatchMsg:
        """A prioritized batch (with replacement) of stored transitions as encoded bytes, with P(i) and
        IS weights. Raises TimeoutError while the rate limiter holds sampling back for timeout_s seconds."""
        drawn, size, datas = self._draw(batch_size, timeout_s, rng,
                                        lambda d: read_batch(self._log, d, self._problem))
        items = tuple(SampleItem(i, p, w, d) for (i, p, w, _), d in zip(drawn, datas, strict=True))
        return SampleBatchMsg(request_id, items, size)

    def sample_encoded(self, batch_size: int, timeout_s: float = 10.0, rng: np.random.Generator | None = None,
                       request_id: str = "local") -> bytearray:
        """sample() as the protobuf SampleBatch the server sends (what wire.encode_sample_batch would give),
        with each transition read from the log straight into its place in the reply (batchcodec)."""
        def read(drawn: Drawn) -> tuple[bytearray, dict[int, str]]:
            return read_batch_encoded(self._log, request_id, len(self._sampler), drawn, self._problem)

        return self._draw(batch_size, timeout_s, rng, read)[2]

    def _problem(self, item_id: int, loc: Location, data: bytes | memoryview) -> str | None:
        """Why the stored record of item_id is damaged, or None (records of legacy segments: unchecked)."""
        if loc.segment in self._legacy_segments:
            return None
        return record_problem(item_id, data)

    def _draw(self, batch_size: int, timeout_s: float, rng: np.random.Generator | None,
              read: Callable[[Drawn], tuple[_T, dict[int, str]]]) -> tuple[Drawn, int, _T]:
        """Draw a batch: ([(id, P(i), IS weight, location)], buffer size, read(that list) under the lock).

        read also returns the damaged items it met (id -> why); they are quarantined and the batch is
        drawn again from what is left, so a batch never holds a record that fails its checksum."""
        if not 1 <= batch_size <= self.cfg.max_batch_size:
            raise ValueError(f"batch_size = {batch_size} is invalid: must be 1..{self.cfg.max_batch_size} "
                             "(replay.max_batch_size)")
        self._limiter.acquire_samples(batch_size, timeout_s)
        found: dict[int, str] = {}
        try:
            with self._lock:
                while True:
                    if not len(self._sampler):
                        self._limiter.cancel_samples(batch_size)
                        raise TimeoutError("the replay buffer is empty")
                    ids, probs = self._sampler.sample(batch_size, rng if rng is not None else self._rng)
                    size = len(self._sampler)
                    beta = annealed_beta(self.cfg.beta0, self._c["sample_batches"], self.cfg.beta_anneal_updates)
                    weights = is_weights(probs, size, beta)
                    drawn = [(int(i), min(1.0, float(p)), float(w), self._location(int(i)))
                             for i, p, w in zip(ids, probs, weights, strict=True)]
                    # Read under the lock: a snapshot may reclaim a segment once its items are evicted.
                    data, bad = read(drawn)
                    if not bad:
                        break
                    for item_id in bad:
                        self._drop(item_id)
                    found.update(bad)
                self._c["sample_batches"] += 1
                self._c["samples"] += batch_size
        finally:
            if found:
                self._losses.record_quarantine(found)
        self._sample_rate.add(batch_size)
        return drawn, size, data

    def _drop(self, item_id: int) -> None:
        """Take a damaged item out of the index for good. Caller holds the lock."""
        if not self._sampler.remove(item_id):
            return
        slot = item_id % self.cfg.capacity_items
        key = self._keys[slot]
        if key is not None:
            self._keys[slot] = None
            self._by_key.pop(key, None)
            self._per_actor_held[key[0]] -= 1
        self._bytes -= int(self._loc[slot, 4])
        self._c["quarantined"] += 1
        self._limiter.set_size(len(self._sampler))

    def update_priorities(self, update: PriorityUpdateMsg) -> int:
        """Apply new priorities by item id; ids no longer held are ignored. Returns the number applied."""
        with self._lock:
            applied = self._sampler.update(update.item_ids, update.priorities)
            self._c["priority_updates"] += applied
            self._c["priority_updates_ignored"] += len(update.item_ids) - applied
        return applied

    def record_rejection(self, reason: str) -> None:
        """Count a rejected input (e.g. 'undecodable', 'wrong_shape') for stats; the server calls this."""
        with self._lock:
            self._rejected[reason] += 1

    def stats(self) -> dict:
        """Size, bytes, counters, rates, priority histogram, top-k, per-actor counts, policy lag, and
        log_fsyncs (fsyncs of log chunks since start: inserts per fsync shows the group commit at work)."""
        with self._lock:
            ids, prios = self._sampler.items()
            pv = self._pv[ids % self.cfg.capacity_items] if len(ids) else np.zeros(0, np.int64)
            out = build_stats(self.cfg, ids, prios, pv, self._latest_policy, dict(self._c), self._bytes,
                              self._insert_rate.rate(), self._sample_rate.rate(), dict(self._per_actor_held),
                              dict(self._per_actor_inserts), dict(self._rejected), self._limiter.counters())
        out["log_fsyncs"] = self._log.fsyncs
        quarantined = self._losses.quarantined()
        out["lost_items"] = self._losses.lost_items  # accepted at a recovery (losses.json)
        out["quarantined_items"] = len(quarantined)
        out["quarantined_ids"] = quarantined[-100:]
        return out

    # ---------------------------------------------------------------------------------------- snapshots
    def snapshot(self) -> Path:
        """Write a snapshot of the index now; then reclaim log segments whose items are all evicted."""
        with self._snapshot_lock:
            with self._lock:
                meta, arrays, next_id, reclaim_below = self._snapshot_state()
                self._since_snapshot = 0
            path = write_snapshot(self.directory, next_id, meta, arrays, self.cfg.keep_snapshots)
            if reclaim_below is not None:
                self._log.delete_segments_below(reclaim_below)
            log.debug("snapshot %s: %d items", path.name, len(arrays["item_id"]))
            return path

    def _snapshot_state(self) -> tuple[dict, dict, int, int | None]:
        ids, prios = self._sampler.items()
        slots = ids % self.cfg.capacity_items
        loc = self._loc[slots]
        arrays, actors, episodes = index_arrays(ids, prios, [self._keys[s] for s in slots.tolist()], loc,
                                                self._pv[slots])
        last = self._last_loc
        next_id = self._next_id - len(self._pending_meta)  # ids at or above are not durable yet
        counters = {"counts": dict(self._c), "per_actor_inserts": dict(self._per_actor_inserts),
                    "rejected": dict(self._rejected), "latest_policy": self._latest_policy,
                    "limiter": self._limiter.counters()}
        meta = {"next_item_id": next_id, "lo": self._lo, "actors": actors, "episodes": episodes,
                "scan_from": None if last is None else [last.segment, last.chunk_offset, last.chunk_first_id],
                "counters": counters}
        reclaim_below = int(loc[0, 0]) if len(ids) else (None if last is None else last.segment)
        return meta, arrays, next_id, reclaim_below

    def _snapshot_loop(self) -> None:
        """Background snapshots every snapshot_every_s seconds or snapshot_every_inserts inserts."""
        last = time.monotonic()
        period = self.cfg.snapshot_every_s or None
        while True:
            self._wake.wait(timeout=min(period, 1.0) if period else None)
            self._wake.clear()
            if self._closed:
                return
            due_time = period is not None and time.monotonic() - last >= period and self._since_snapshot
            due_count = self._since_snapshot >= self.cfg.snapshot_every_inserts > 0
            if due_time or due_count:
                try:
                    self.snapshot()
                except OSError:
                    log.exception("replay snapshot failed; the log still holds every acknowledged item")
                last = time.monotonic()

    def close(self) -> None:
        """Stop waiting calls, write a final snapshot, finish the log segment. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._limiter.close()
        self._wake.set()
        self._snapshotter.join(timeout=30)
        try:
            self._log.close()
            with self._lock:
                self._publish()
            self.snapshot()
        finally:
            self._dir_lock.release()

    def __enter__(self) -> ReplayStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

