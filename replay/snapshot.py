"""Snapshots of the replay index: `snapshot-<next item id, 12 digits>.npz` (numpy arrays + a JSON table).

Written to `<name>.tmp`, fsync'ed, renamed, and the directory fsync'ed, so a crash leaves either the
old or the new snapshot, never half of one; leftover `.tmp` files are ignored and removed. Loaded with
allow_pickle=False: a snapshot holds numbers and one JSON document (stored as uint8 bytes), never
pickled objects. The newest snapshot that loads is used; an unreadable one is skipped with a warning.
"""

from __future__ import annotations

import json
import logging
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from romannet.common.fsutil import fsync_directory

log = logging.getLogger(__name__)

FORMAT = 1
_PREFIX = "snapshot-"
_META_KEY = "meta_json"


def snapshot_files(directory: Path) -> list[Path]:
    """Complete snapshot files, oldest first."""
    paths = [p for p in directory.glob(f"{_PREFIX}*.npz") if p.stem[len(_PREFIX):].isdigit()]
    return sorted(paths, key=lambda p: int(p.stem[len(_PREFIX):]))


def write_snapshot(directory: Path, sequence: int, meta: dict[str, Any], arrays: dict[str, np.ndarray],
                   keep: int = 2) -> Path:
    """Atomically write a snapshot named by `sequence` (monotonic), then delete all but the `keep` newest."""
    path = directory / f"{_PREFIX}{sequence:012d}.npz"
    tmp = path.with_name(path.name + ".tmp")
    payload = dict(arrays)
    payload[_META_KEY] = np.frombuffer(json.dumps({"format": FORMAT, **meta}).encode(), dtype=np.uint8)
    with tmp.open("wb") as fh:
        np.savez(fh, **payload)  # uncompressed: the arrays are small and it keeps snapshots fast
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    fsync_directory(directory)
    for old in snapshot_files(directory)[:-keep]:
        old.unlink(missing_ok=True)
    return path


def index_arrays(ids: np.ndarray, priorities: np.ndarray, keys: list[Any], loc: np.ndarray,
                 policy_versions: np.ndarray) -> tuple[dict[str, np.ndarray], list[str], list[int]]:
    """A snapshot's arrays for the items held (ids, priorities, idempotency keys (actor, episode, step),
    Location rows, policy versions), with the actor and episode tables their `actor`/`episode` index."""
    actors = sorted({k[0] for k in keys if k})
    episodes = sorted({k[1] for k in keys if k})
    a_index = {a: i for i, a in enumerate(actors)}
    e_index = {e: i for i, e in enumerate(episodes)}
    arrays = {
        "item_id": ids, "priority": priorities, "segment": loc[:, 0], "chunk_offset": loc[:, 1],
        "chunk_first_id": loc[:, 2], "data_offset": loc[:, 3], "length": loc[:, 4],
        "policy_version": policy_versions,
        "actor": np.array([a_index[k[0]] for k in keys if k], dtype=np.int32),
        "episode": np.array([e_index[k[1]] for k in keys if k], dtype=np.int64),
        "step": np.array([k[2] for k in keys if k], dtype=np.int64),
    }
    return arrays, actors, episodes


def _load(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    meta = json.loads(arrays.pop(_META_KEY).tobytes().decode())
    if meta.get("format") != FORMAT:
        raise ValueError(f"snapshot format {meta.get('format')!r}; this version reads {FORMAT}")
    return meta, arrays


def load_latest(directory: Path, clean: bool = True) -> tuple[Path, dict[str, Any], dict[str, np.ndarray]] | None:
    """(path, meta, arrays) of the newest readable snapshot, or None. Removes leftover .tmp files when
    `clean` (not while a server may be writing one: `romannet replay --check`)."""
    for tmp in directory.glob(f"{_PREFIX}*.npz.tmp") if clean else ():
        log.info("ignoring %s: an unfinished snapshot from a crash", tmp.name)
        tmp.unlink(missing_ok=True)
    for path in reversed(snapshot_files(directory)):
        try:
            meta, arrays = _load(path)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            log.warning("skipping unreadable snapshot %s: %s", path.name, exc)
            continue
        return path, meta, arrays
    return None
