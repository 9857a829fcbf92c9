"""Small file-system helpers for the durability paths (spool, replay log, checkpoints) and run files."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any


def fsync_directory(directory: str | Path) -> None:
    """Make a file creation, rename or deletion in `directory` durable (the entry, not the file's data)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_text_atomic(path: Path, text: str) -> None:
    """Replace `path` with `text` all at once (tmp file + rename): a reader or a crash sees the old file or
    the new one, never half of one. No fsync: for files rewritten often (statuses, counts, reports)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def write_json_atomic(path: Path, data: Any, indent: int = 1) -> None:
    """`write_text_atomic` of `data` as JSON."""
    write_text_atomic(path, json.dumps(data, indent=indent) + "\n")
