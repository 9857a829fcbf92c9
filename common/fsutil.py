"""Small file-system helpers for the durability paths (spool, replay log, checkpoints)."""

from __future__ import annotations

import os
from pathlib import Path


def fsync_directory(directory: str | Path) -> None:
    """Make a file creation, rename or deletion in `directory` durable (the entry, not the file's data)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
