"""`romannet bench chaos`'s damaged copies (bench/chaos_damage.py) on a real replay directory: the live
directory is never touched, and every item the flipped bytes cost is reported, none silently."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from _replay_helpers import cfg, crash, segments, tr

from romannet.bench.chaos_damage import damage_copy
from romannet.replay.check import check_directory
from romannet.replay.store import ReplayStore


def test_flipped_bytes_in_a_copy_are_all_reported_and_the_original_is_untouched(tmp_path: Path) -> None:
    live = tmp_path / "replay"
    store = ReplayStore(cfg(), live)
    for step in range(60):
        assert store.insert(tr(step)).status == "accepted"
    store.snapshot()
    for step in range(60, 90):  # a log tail after the snapshot, as a killed server leaves it
        store.insert(tr(step))
    crash(store)
    before = {p.name: p.read_bytes() for p in segments(live)}

    total = {"damaged_reported": 0, "lost_reported": 0}
    for seed in range(4):
        report = damage_copy(live, tmp_path / "copies" / f"{seed}", np.random.default_rng(seed), flips=6)
        assert report["held_before"] == 90 and report["flipped_bytes"] == 6
        assert report["unreported"] == 0, report
        assert report["recovered"] + report["damaged_reported"] + report["lost_reported"] >= 90, report
        for k in total:
            total[k] += report[k]
    assert sum(total.values()) > 0  # 24 flipped bytes in ~90 records: some cost something
    assert {p.name: p.read_bytes() for p in segments(live)} == before
    assert check_directory(live).ok and not list((tmp_path / "copies").iterdir())
