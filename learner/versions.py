"""Weights and exploration versions that never name two different sets of weights, across crashes too.

    clock = VersionClock.start(run_dir, updates=trainer.updates, saved_offset=0, resumed_from=None, block=10)
    publisher.publish_weights(clock.claim(trainer.updates), tensors)   # version = updates + clock.offset
    clock.release(trainer.updates, checkpoint_name)                    # after the clean stop's checkpoint

A version is the update count plus an offset (0 for a run that never crashed). Before a version is
published, the learner reserves a block of versions in RUN_DIR/checkpoints/versions.json (written whole:
temporary file, fsync, rename, directory fsync), so the file always holds a bound on every version ever
published. A learner that resumes from a checkpoint older than that bound (a kill -9 after the last
checkpoint, or a damaged newest checkpoint) or starts fresh over a run that published before takes a new
offset, so its first version is above the bound: the updates it repeats get new numbers. After a clean
stop the reservation is released down to the last version, which names exactly the final checkpoint's
weights, so a clean stop and resume keeps versions equal to update counts.

Each checkpoint records the offset it was trained under (state.json "version_offset").
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

from romannet.common.errors import RomannetError
from romannet.common.fsutil import fsync_directory

log = logging.getLogger(__name__)

VERSIONS_FILE = "versions.json"


def versions_path(run_dir: str | Path) -> Path:
    """Where a run's version reservation lives (next to its checkpoints)."""
    return Path(run_dir) / "checkpoints" / VERSIONS_FILE


def read_reservation(run_dir: str | Path) -> dict[str, Any]:
    """{"reserved": highest version possibly published (-1: none), "clean_stop": checkpoint name or None}.
    RomannetError when the file is there but unreadable: guessing a bound could reuse versions."""
    path = versions_path(run_dir)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {"reserved": -1, "clean_stop": None}
    except (OSError, ValueError) as err:
        raise RomannetError(f"{path} is unreadable ({err}): it bounds the weights versions already published; "
                           "restore it or remove it knowing versions may repeat") from None
    reserved = data.get("reserved") if isinstance(data, dict) else None
    if not isinstance(reserved, int) or isinstance(reserved, bool):
        raise RomannetError(f"{path} holds no integer 'reserved' version: restore it or remove it")
    return {"reserved": reserved, "clean_stop": data.get("clean_stop")}


def _write(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(json.dumps(data).encode())
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_directory(path.parent)


class VersionClock:
    """The versions of one learner process: updates + offset, each reserved on disk before use."""

    def __init__(self, path: Path, offset: int, reserved: int, block: int):
        self.path, self.offset, self.reserved, self.block = path, offset, reserved, max(1, block)

    @classmethod
    def start(cls, run_dir: str | Path, updates: int, saved_offset: int, resumed_from: str | None,
              block: int) -> VersionClock:
        """The clock of a learner at `updates` (its checkpoint's version_offset, or 0 for a fresh start);
        the offset grows when the version of these weights may already name others."""
        res = read_reservation(run_dir)
        reserved, first = res["reserved"], updates + saved_offset
        same_weights = first == reserved and resumed_from is not None and res["clean_stop"] == resumed_from
        offset = saved_offset if first > reserved or same_weights else reserved + 1 - updates
        if offset != saved_offset:
            log.warning("weights versions up to %d may have been published before (a crash, or a resume from an "
                        "older checkpoint): update %d is published as version %d", reserved, updates,
                        updates + offset)
        return cls(versions_path(run_dir), offset, reserved, block)

    def version(self, updates: int) -> int:
        """The version of the weights (and exploration rate) at update count `updates`."""
        return updates + self.offset

    def claim(self, updates: int) -> int:
        """The version of `updates`, reserved on disk (with a block of following ones) before it is returned."""
        version = self.version(updates)
        if version > self.reserved:
            self.reserved = version + self.block - 1
            _write(self.path, {"reserved": self.reserved, "clean_stop": None})
        return version

    def release(self, updates: int, checkpoint: str) -> None:
        """After a clean stop: the last version is that of `updates`, whose weights are `checkpoint`'s."""
        self.reserved = self.version(updates)
        _write(self.path, {"reserved": self.reserved, "clean_stop": checkpoint})
