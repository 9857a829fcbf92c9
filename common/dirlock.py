"""One writer per directory: an advisory `flock` on `<dir>/LOCK`, a file holding the holder's pid.

The replay store (replay/store.py) takes it before it reads or repairs anything, so a second replay server
on a directory in use stops at once with one line ("replay directory D is in use by pid 1234") instead of
truncating the first one's log tail or refusing every insert. The kernel drops the lock when the holder's
file descriptor closes, so a process killed with SIGKILL never leaves a stale lock behind; the LOCK file
itself stays (removing it could let two processes lock two different files of the same name). The
descriptor is not inherited by child processes (Python opens files non-inheritable).
"""

from __future__ import annotations

import fcntl
import logging
import os
import time
from pathlib import Path

from .errors import RomannetError

LOCK_FILE = "LOCK"
log = logging.getLogger(__name__)


class DirectoryInUseError(RomannetError):
    """Another process holds the directory's lock; the message names the directory and the holder's pid."""

    def __init__(self, what: str, directory: Path, pid: int | None):
        self.directory, self.pid = directory, pid
        holder = f"pid {pid}" if pid is not None else "another process"
        super().__init__(f"{what} {directory} is in use by {holder}")


def _holder_pid(fd: int) -> int | None:
    """The pid written in a lock file another process holds (None if unreadable: it may be writing it now)."""
    for _ in range(20):
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        if text.isdigit():
            return int(text)
        time.sleep(0.01)
    return None


class DirectoryLock:
    """`DirectoryLock(directory, what)` holds the lock until `release()` (or the process ends)."""

    def __init__(self, directory: str | Path, what: str = "directory"):
        self.path = Path(directory) / LOCK_FILE
        self._fd: int | None = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = _holder_pid(self._fd)
            self._close()
            raise DirectoryInUseError(what, Path(directory), pid) from None
        except BaseException:
            self._close()
            raise
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, f"{os.getpid()}\n".encode(), 0)
        log.debug("locked %s (pid %d)", self.path, os.getpid())

    @property
    def held(self) -> bool:
        return self._fd is not None

    def _close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def release(self) -> None:
        """Give the directory up (idempotent): the pid is cleared, then the descriptor closed."""
        if self._fd is not None:
            os.ftruncate(self._fd, 0)
            self._close()

    def __enter__(self) -> DirectoryLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def check_not_locked(directory: str | Path, what: str = "directory") -> None:
    """Raise DirectoryInUseError if a process holds `directory`'s lock now (nothing is created if the
    directory does not exist). A check, not a claim: the writer takes the lock itself when it starts."""
    if Path(directory).is_dir():
        DirectoryLock(directory, what).release()
