"""Rate limiter with Reverb's semantics (reverb/cc/rate_limiter.cc), for whole batches.

- Sampling waits until the buffer holds `min_size_to_sample` items.
- Optional samples-per-insert ratio: with d = spi * inserts - samples and offset = spi * min_size,
  an insert waits while d + spi > offset + tolerance (the learner is behind), and a batch of B samples
  waits while d - B < offset - tolerance (the actors are behind). `inserts` counts every insert ever
  made (evictions do not give credit back), `samples` every sampled item, as in Reverb.
- Inserts are never held back before the buffer reaches min_size_to_sample.

Waiting uses one Condition; every wait has a timeout and raises TimeoutError saying what it waited for.
ReplayConfig refuses settings that could deadlock, so a wait only lasts while the other side is idle.
"""

from __future__ import annotations

import threading
import time


class LimiterClosed(RuntimeError):
    """The store is closing; waiting calls give up."""


class RateLimiter:
    """Thread-safe insert/sample admission. Counters are restored from a snapshot with `restore`."""

    def __init__(self, min_size_to_sample: int, samples_per_insert: float | None = None,
                 tolerance: float = 0.0):
        self.min_size_to_sample = int(min_size_to_sample)
        self.samples_per_insert = samples_per_insert
        offset = (samples_per_insert or 0.0) * self.min_size_to_sample
        self._min_diff = offset - tolerance
        self._max_diff = offset + tolerance
        self._cond = threading.Condition()
        self._inserts = 0  # admitted inserts, ever
        self._samples = 0  # sampled items, ever
        self._size = 0  # items in the buffer now
        self._closed = False

    # ------------------------------------------------------------------------------ predicates (locked)
    def _can_insert(self) -> bool:
        if self.samples_per_insert is None or self._inserts + 1 <= self.min_size_to_sample:
            return True
        return (self._inserts + 1) * self.samples_per_insert - self._samples <= self._max_diff

    def _can_sample(self, n: int) -> bool:
        if self._size < self.min_size_to_sample:
            return False
        if self.samples_per_insert is None:
            return True
        return self._inserts * self.samples_per_insert - (self._samples + n) >= self._min_diff

    def _wait(self, ready: object, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not ready():  # type: ignore[operator]
            if self._closed:
                raise LimiterClosed(f"replay store closed while waiting to {what}")
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"rate limiter held {what} for {timeout_s:g} s ({self._describe()})")
            self._cond.wait(left)

    def _describe(self) -> str:
        text = f"size {self._size}, min_size_to_sample {self.min_size_to_sample}"
        if self.samples_per_insert is not None:
            text += (f", inserts {self._inserts}, samples {self._samples}, samples_per_insert "
                     f"{self.samples_per_insert:g}, allowed spi*inserts - samples in "
                     f"[{self._min_diff:g}, {self._max_diff:g}]")
        return text

    # ------------------------------------------------------------------------------------------ public
    def acquire_insert(self, timeout_s: float) -> None:
        """Wait (at most timeout_s seconds) until one insert is allowed, and count it."""
        with self._cond:
            self._wait(self._can_insert, timeout_s, "an insert")
            self._inserts += 1
            self._cond.notify_all()

    def cancel_insert(self) -> None:
        """Give back an admitted insert that was not stored (duplicate found late, write failed)."""
        with self._cond:
            self._inserts -= 1
            self._cond.notify_all()

    def acquire_samples(self, n: int, timeout_s: float) -> None:
        """Wait (at most timeout_s seconds) until a batch of n samples is allowed, and count it."""
        with self._cond:
            self._wait(lambda: self._can_sample(n), timeout_s, f"a batch of {n} samples")
            self._samples += n
            self._cond.notify_all()

    def cancel_samples(self, n: int) -> None:
        """Give back admitted samples that were not served."""
        with self._cond:
            self._samples -= n
            self._cond.notify_all()

    def set_size(self, size: int) -> None:
        """The buffer now holds `size` items (after inserts became visible, or evictions)."""
        with self._cond:
            self._size = size
            self._cond.notify_all()

    def restore(self, inserts: int, samples: int, size: int) -> None:
        """Counters after recovery."""
        with self._cond:
            self._inserts, self._samples, self._size = inserts, samples, size
            self._cond.notify_all()

    def counters(self) -> dict[str, int]:
        with self._cond:
            return {"inserts": self._inserts, "samples": self._samples, "size": self._size}

    def close(self) -> None:
        """Wake every waiter; they raise LimiterClosed."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
