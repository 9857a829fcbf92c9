"""Flipped bytes in a copy of a live replay directory, and whether every item they cost is reported.

    report = damage_copy(run_dir / "replay", work / "copies" / "kill-001", rng, flips=8)

The copy is checked twice with `romannet replay --check`'s own code (replay/check.py, which reads without
writing): before the flips (what recovery would hold) and after. Every item held before must be held and
intact after, or reported: as damaged (its record's checksum fails: quarantined when read) or as lost
(recovery names it). `unreported` counts the rest, silent losses, and must be 0. Only log segments are
damaged: they hold the transitions; snapshots are an index rebuilt from them.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np

from romannet.replay.check import check_directory


def _flip(segments: list[Path], rng: np.random.Generator, flips: int) -> list[dict[str, Any]]:
    """Flip one random bit in each of `flips` random bytes, files chosen in proportion to their size."""
    sizes = np.array([p.stat().st_size for p in segments], dtype=np.float64)
    done = []
    if not segments or sizes.sum() == 0:
        return done
    for _ in range(flips):
        path = segments[int(rng.choice(len(segments), p=sizes / sizes.sum()))]
        offset = int(rng.integers(0, path.stat().st_size))
        with path.open("r+b") as fh:
            fh.seek(offset)
            byte = fh.read(1)[0]
            fh.seek(offset)
            fh.write(bytes([byte ^ (1 << int(rng.integers(8)))]))
        done.append({"file": path.name, "offset": offset})
    return done


def damage_copy(replay_dir: Path, copy: Path, rng: np.random.Generator, flips: int,
                keep: bool = False) -> dict[str, Any]:
    """Copy replay_dir to `copy` (a new path), check it, flip `flips` bytes in its segments, check again;
    see the module docstring. The copy is removed afterwards unless keep."""
    copy.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(replay_dir, copy, ignore=shutil.ignore_patterns("LOCK", "*.tmp"))
    try:
        before = check_directory(copy)
        flipped = _flip(sorted(copy.glob("segment-*.mcap")), rng, flips)
        after = check_directory(copy)
    finally:
        if not keep:
            shutil.rmtree(copy, ignore_errors=True)
    lost = sum(loss.count for loss in after.unaccepted)
    intact = after.held - len(after.damaged)
    uncounted = any(loss.uncounted for loss in after.unaccepted)
    return {
        "copy": copy.name, "held_before": before.held, "damaged_before": len(before.damaged),
        "flipped_bytes": len(flipped), "recovered": intact, "damaged_reported": len(after.damaged),
        "lost_reported": lost, "loss_uncounted": uncounted,
        # Held before, neither recovered intact nor named as damaged or lost (with an uncounted loss the
        # count is open, so only a shortfall beyond it shows).
        "unreported": max(0, before.held - len(before.damaged) - intact - len(after.damaged) - lost),
    }
