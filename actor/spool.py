"""A bounded on-disk spool of encoded transitions: written before sending, removed once acknowledged.

Layout of the spool directory (one file per item, no pickle — the files hold wire.encode_transition bytes):

    <dir>/<seq:012d>.pb          pending transitions, sent oldest first (seq = order of writing)
    <dir>/tmp/                   items being written (leftovers of a crash are deleted on open)
    <dir>/rejected/<name>.pb     transitions the replay server refused, kept for inspection ...
    <dir>/rejected/<name>.json   ... with the reason

Crash safety: an item is written to tmp/, fsync'ed, renamed into place and the directory fsync'ed, so a
`<seq>.pb` file is always complete. A crash between the server's ack and the file's removal resends the
item on the next start; the server's idempotent key (actor_id, episode_id, step) answers "duplicate", which
is an acknowledgement like any other, so nothing is lost and nothing is stored twice.

The bound (items and bytes) is enforced by the producer: `wait_for_room` blocks the actor before it takes
the next action while the spool is full, so the spool exceeds the bound by at most the one transition of
the action under way. Thread-safe: the actor loop writes, the sender thread reads and removes.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path

from romannet.common.fsutil import fsync_directory

log = logging.getLogger(__name__)

_SUFFIX = ".pb"



class Spool:
    """Pending transitions in `directory`, at most max_items items / max_bytes bytes before producers wait."""

    def __init__(self, directory: str | Path, max_items: int, max_bytes: int, fsync: bool = True):
        self.dir = Path(directory)
        self.max_items, self.max_bytes, self.fsync = int(max_items), int(max_bytes), bool(fsync)
        self._tmp = self.dir / "tmp"
        self.rejected_dir = self.dir / "rejected"
        for d in (self.dir, self._tmp, self.rejected_dir):
            d.mkdir(parents=True, exist_ok=True)
        for stale in self._tmp.iterdir():  # half-written items of a crash: never acknowledged, never sent
            stale.unlink(missing_ok=True)
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._sizes: dict[int, int] = {}  # seq -> bytes, pending items only
        for f in self.dir.glob(f"*{_SUFFIX}"):
            if f.stem.isdigit():
                self._sizes[int(f.stem)] = f.stat().st_size
        self._bytes = sum(self._sizes.values())
        self._next_seq = max(self._sizes, default=-1) + 1
        self.recovered = len(self._sizes)  # items found on open: written by an earlier run, not yet acked
        self.rejected = 0
        if self.recovered:
            log.info("spool %s: %d transition(s) (%d bytes) from an earlier run will be resent",
                     self.dir, self.recovered, self._bytes)

    # ---------------------------------------------------------------------------------------- state
    @property
    def items(self) -> int:
        """Pending (written, not yet acknowledged) transitions."""
        with self._lock:
            return len(self._sizes)

    @property
    def bytes(self) -> int:
        """Bytes of the pending transitions."""
        with self._lock:
            return self._bytes

    def full(self) -> bool:
        """True while the spool holds max_items items or max_bytes bytes (the producer should wait)."""
        with self._lock:
            return self._full_locked()

    def _full_locked(self) -> bool:
        return len(self._sizes) >= self.max_items or self._bytes >= self.max_bytes

    def _path(self, seq: int) -> Path:
        return self.dir / f"{seq:012d}{_SUFFIX}"

    # ------------------------------------------------------------------------------------- producer
    def put(self, data: bytes) -> int:
        """Write one encoded transition durably and return its sequence number. Never blocks on the bound
        (call wait_for_room before taking the action); raises OSError if the disk refuses."""
        with self._lock:
            seq = self._next_seq
            self._next_seq += 1
        tmp = self._tmp / f"{seq:012d}.tmp"
        with open(tmp, "wb") as f:
            f.write(data)
            if self.fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, self._path(seq))
        if self.fsync:
            fsync_directory(self.dir)
        with self._lock:
            self._sizes[seq] = len(data)
            self._bytes += len(data)
            self._changed.notify_all()
        return seq

    def wait_for_room(self, timeout_s: float) -> bool:
        """Wait up to timeout_s seconds until the spool is below its bound; True if it is."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._full_locked():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._changed.wait(remaining)
            return True

    # ------------------------------------------------------------------------------------- consumer
    def wait_for_item(self, timeout_s: float) -> int | None:
        """The oldest pending item's sequence number, waiting up to timeout_s seconds for one."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while not self._sizes:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._changed.wait(remaining)
            return min(self._sizes)

    def read(self, seq: int) -> bytes:
        """The bytes of pending item seq."""
        return self._path(seq).read_bytes()

    def remove(self, seq: int) -> None:
        """Forget an acknowledged item (its file is deleted)."""
        self._path(seq).unlink(missing_ok=True)
        # No directory fsync: if the unlink is lost in a crash the item is resent and acked as duplicate.
        self._forget(seq)

    def reject(self, seq: int, reason: str, key: str = "") -> Path:
        """Move a refused item to rejected/ with a JSON note of the reason; returns the moved file's path."""
        name = f"{time.time_ns()}-{seq:012d}"
        target = self.rejected_dir / f"{name}{_SUFFIX}"
        note = {"seq": seq, "key": key, "reason": reason, "time_ns": time.time_ns()}
        (self.rejected_dir / f"{name}.json").write_text(json.dumps(note, indent=1) + "\n", encoding="utf-8")
        os.replace(self._path(seq), target)
        if self.fsync:
            fsync_directory(self.rejected_dir)
            fsync_directory(self.dir)
        with self._lock:
            self.rejected += 1
        self._forget(seq)
        return target

    def _forget(self, seq: int) -> None:
        with self._lock:
            size = self._sizes.pop(seq, None)
            if size is not None:
                self._bytes -= size
            self._changed.notify_all()

    def wait_until_empty(self, timeout_s: float) -> bool:
        """Wait up to timeout_s seconds until nothing is pending; True if empty."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._sizes:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._changed.wait(remaining)
            return True
