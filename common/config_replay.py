"""Configuration of the replay server's buffer: capacity, prioritization, rate limiting, durability.

One frozen dataclass, validated on construction: a bad value raises ConfigError naming the field, the
value and the fix. Rate-limiter settings that could block inserts and samples forever are refused here,
at start-up, with the arithmetic that shows why (Reverb's SampleToInsertRatio rules, for whole batches).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .configbase import require

_GIB = 1 << 30


@dataclass(frozen=True)
class ReplayConfig:
    """Prioritized replay buffer (stochastic rank-based, Schaul et al. 2016) with a durable log."""

    # Capacity: the oldest items are evicted first when either limit would be exceeded.
    capacity_items: int = 100_000
    capacity_bytes: int = 32 * _GIB  # encoded transition bytes held (PNG heightmaps, ~0.1-0.3 MB each)
    max_item_bytes: int = 16 * (1 << 20)  # larger transitions are rejected
    # Sampling: P(i) ∝ rank(i)^-alpha; IS weights (N P(i))^-beta with beta annealed beta0 -> 1.
    alpha: float = 0.7  # Schaul et al.'s rank-based choice
    beta0: float = 0.5
    beta_anneal_updates: int = 100_000  # sampled batches (learner updates) until beta reaches 1
    max_batch_size: int = 8  # largest batch one sample call may ask for (the learner's batch_size is 4)
    # Rate limiting (Reverb semantics). The defaults pace actors and a learner sharing one small box at four
    # trained transitions per action (twice VPG's; it beat two on the 3-seed clutter sweep, docs/results.md):
    # an insert's ack waits while the learner is more than a few updates behind, and the actor's small spool
    # (actor.spool_max_items) makes it wait, so learning per action does not depend on the machine's speed.
    min_size_to_sample: int = 64  # items in the buffer before any sample is served
    samples_per_insert: float = 4.0  # 0 = no ratio limit (TOML has no null to say "unset")
    spi_tolerance: float = 8.0  # Reverb's error_buffer: allowed drift of samples - spi * inserts
    # Durability.
    segment_max_bytes: int = 256 * (1 << 20)  # log segment rotation size
    fsync: bool = True  # False only for throw-away runs: acks then survive a process crash, not power loss
    snapshot_every_s: float = 60.0  # 0 = no time-based snapshots
    snapshot_every_inserts: int = 1000  # 0 = no count-based snapshots
    keep_snapshots: int = 2  # older snapshots are deleted; the previous one is a fallback if the last is bad
    # Stats.
    histogram_bins: int = 10
    top_k: int = 10

    def __post_init__(self) -> None:
        require(1 <= self.capacity_items <= 100_000_000, "replay.capacity_items", self.capacity_items,
                "must be 1..100000000 items")
        require(self.capacity_bytes >= 1 << 20, "replay.capacity_bytes", self.capacity_bytes,
                "must be at least 1 MiB (1048576); one 224x224 transition is ~0.1-0.3 MB")
        require(1024 <= self.max_item_bytes <= min(self.capacity_bytes, 64 << 20), "replay.max_item_bytes",
                self.max_item_bytes, "must be 1 KiB..min(capacity_bytes, 64 MiB)")
        require(0.0 <= self.alpha <= 5.0, "replay.alpha", self.alpha,
                "must be in [0, 5] (0 = uniform; Schaul et al. use 0.7 for rank-based)")
        require(0.0 <= self.beta0 <= 1.0, "replay.beta0", self.beta0, "must be in [0, 1] (Schaul et al.: 0.5)")
        require(self.beta_anneal_updates >= 0, "replay.beta_anneal_updates", self.beta_anneal_updates,
                "must be >= 0 (0 = beta is 1 from the start)")
        require(1 <= self.max_batch_size <= 4096, "replay.max_batch_size", self.max_batch_size,
                "must be 1..4096 (the wire limit)")
        require(self.min_size_to_sample >= 1, "replay.min_size_to_sample", self.min_size_to_sample,
                "must be >= 1")
        require(self.min_size_to_sample <= self.capacity_items, "replay.min_size_to_sample",
                self.min_size_to_sample,
                f"must be <= capacity_items ({self.capacity_items}): the buffer could never hold enough "
                "items to start sampling, so every sample would block forever")
        require(math.isfinite(self.spi_tolerance) and self.spi_tolerance >= 0, "replay.spi_tolerance",
                self.spi_tolerance, "must be a finite number >= 0")
        if self.samples_per_insert != 0:
            self._check_ratio()
        require(self.segment_max_bytes >= 1 << 20, "replay.segment_max_bytes", self.segment_max_bytes,
                "must be >= 1 MiB (1048576); a segment is rotated before the chunk that would overflow it")
        require(self.snapshot_every_s >= 0, "replay.snapshot_every_s", self.snapshot_every_s,
                "must be >= 0 seconds (0 = off)")
        require(self.snapshot_every_inserts >= 0, "replay.snapshot_every_inserts", self.snapshot_every_inserts,
                "must be >= 0 (0 = off)")
        require(self.keep_snapshots >= 1, "replay.keep_snapshots", self.keep_snapshots, "must be >= 1")
        require(1 <= self.histogram_bins <= 1000, "replay.histogram_bins", self.histogram_bins, "must be 1..1000")
        require(0 <= self.top_k <= 1000, "replay.top_k", self.top_k, "must be 0..1000")

    @property
    def spi_limit(self) -> float | None:
        """The samples-per-insert ratio the limiter enforces, None for none (samples_per_insert = 0)."""
        return self.samples_per_insert or None

    def _check_ratio(self) -> None:
        """Refuse a samples-per-insert limiter that can reach a state where neither side may proceed.

        With d = spi * inserts - samples, a batch of B samples needs d - B >= lo and an insert needs
        d + spi <= hi, where [lo, hi] = offset -/+ spi_tolerance. Both are refused at once for some
        reachable d unless hi - lo >= B + spi, i.e. 2 * spi_tolerance >= max_batch_size + spi.
        """
        spi = self.samples_per_insert
        require(math.isfinite(spi) and spi > 0, "replay.samples_per_insert", spi,
                "must be a finite number > 0, or 0 for no ratio limit")
        need = self.max_batch_size + spi
        require(2 * self.spi_tolerance >= need, "replay.spi_tolerance", self.spi_tolerance,
                f"with samples_per_insert = {spi} and max_batch_size = {self.max_batch_size} the limiter can "
                f"deadlock: a batch needs {self.max_batch_size} samples of slack and an insert {spi}, so "
                f"2 * spi_tolerance must be >= {need:g}; set spi_tolerance >= {need / 2:g} (or lower "
                "max_batch_size)")

