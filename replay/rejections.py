"""Why the replay server refused a message: a short reason token per failure, counted and log-throttled.

Pure bookkeeping, no transport: the server calls `Rejections.record(kind, reason, detail)` and puts
`snapshot()` in its stats. The reason tokens are part of the protocol: they start the error reply
(`<reason>: <detail>`) and clients branch on some of them (e.g. "rate_limited").
"""

from __future__ import annotations

import logging
import threading
from collections import Counter

log = logging.getLogger(__name__)

# Log the first few rejections of each reason in full, then only every n-th: a fuzzer or a broken actor
# can send thousands of bad messages, and the log must stay readable.
_LOG_FIRST = 5
_LOG_EVERY = 100

# (substring of a DecodeError message, reason), checked in order; messages come from common/wire.py.
_DECODE_REASONS = (
    ("bytes; at most", "oversized"),
    ("schema_version", "schema_version"),
    ("not a protobuf", "undecodable"),
    ("missing field", "missing_field"),
    (" nan ", "non_finite"),
    (" inf ", "non_finite"),
    ("non-finite", "non_finite"),
    ("differ in size", "wrong_shape"),
    ("heightmap size", "wrong_shape"),
    ("pixels", "wrong_shape"),
    ("png", "bad_image"),
)


def classify_decode_error(message: str) -> str:
    """The reason token for a DecodeError message ("invalid" when no rule matches)."""
    text = f" {message.lower()} "
    for needle, reason in _DECODE_REASONS:
        if needle in text:
            return reason
    return "invalid"


class Rejections:
    """Thread-safe counters of refused messages by (kind, reason), e.g. ("insert", "non_finite")."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[tuple[str, str]] = Counter()

    def record(self, kind: str, reason: str, detail: str) -> None:
        """Count one refused message of `kind` ("insert", "sample", "priorities", ...) and log it."""
        with self._lock:
            self._counts[(kind, reason)] += 1
            n = self._counts[(kind, reason)]
        if n <= _LOG_FIRST or n % _LOG_EVERY == 0:
            log.warning("rejected %s (%s, %d so far): %.300s", kind, reason, n, detail)

    def total(self) -> int:
        """Number of refused messages of every kind and reason."""
        with self._lock:
            return sum(self._counts.values())

    def snapshot(self) -> dict[str, dict[str, int]]:
        """{kind: {reason: count}} for the stats reply."""
        with self._lock:
            out: dict[str, dict[str, int]] = {}
            for (kind, reason), n in sorted(self._counts.items()):
                out.setdefault(kind, {})[reason] = n
            return out
