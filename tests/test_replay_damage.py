"""Replay damage on disk: real segment files damaged with real bytes.

A damaged record costs only itself (records carry their own checksum; the scan resynchronises at the
next good one); a missing or emptied segment is named with the exact ids and the store refuses to go on
until the loss is accepted (then recorded in losses.json, never sealed silently by the next snapshot);
damage in an already-snapshotted segment is found when read (quarantined, never sampled again, in stats)
and by `romannet replay --check DIR`; the learner decodes a batch item by item.
"""

from __future__ import annotations

import json
import logging
import struct

import numpy as np
import pytest
from _replay_helpers import cfg, crash, segments, tr

from romannet.cli import main as cli_main
from romannet.common.wire import encode_transition
from romannet.learner.batches import decode_batch_tolerant
from romannet.replay.log import SegmentLog
from romannet.replay.losses import ReplayLossError
from romannet.replay.recovery import priority_suffix
from romannet.replay.store import ReplayStore


def _held(store: ReplayStore) -> list[int]:
    return sorted(store._sampler.items()[0].tolist())


def _log_chunks(directory, n_chunks: int, per_chunk: int) -> list[list[int]]:
    """Write n_chunks group commits of per_chunk records each, as the store does; the ids per chunk."""
    log = SegmentLog(directory, 1 << 30)
    chunks = []
    for c in range(n_chunks):
        ids = list(range(c * per_chunk, (c + 1) * per_chunk))
        tickets = [log.append(i, encode_transition(tr(i, seed=i)), 1, priority_suffix(1.0)) for i in ids]
        log.sync(tickets[-1])  # one fsync, one chunk
        chunks.append(ids)
    log.close()
    return chunks


def _record_offsets(path) -> dict[int, tuple[int, int]]:
    """item id -> (offset of its message record, record length), by walking the file's framing."""
    data = path.read_bytes()
    out, pos = {}, 8
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        if opcode == 0x06:
            pos += 49  # into the chunk: its records follow the fixed chunk header (49 bytes)
            continue
        if opcode == 0x05:
            out[struct.unpack_from("<I", data, pos + 11)[0]] = (pos, 9 + length)
        pos += 9 + length
    return out


def _damage(path, offset: int, new: bytes) -> None:
    data = bytearray(path.read_bytes())
    data[offset:offset + len(new)] = new
    path.write_bytes(bytes(data))


def test_flipped_bytes_mid_segment_cost_only_the_damaged_record(tmp_path, caplog) -> None:
    chunks = _log_chunks(tmp_path, n_chunks=10, per_chunk=10)  # 100 acknowledged items in 10 chunks
    seg = segments(tmp_path)[-1]
    offset, length = _record_offsets(seg)[45]
    data = bytearray(seg.read_bytes())
    for k in range(5):  # 5 flipped bytes in the middle of item 45's transition bytes
        data[offset + length // 2 + 7 * k] ^= 0xFF
    seg.write_bytes(bytes(data))
    before = seg.read_bytes()
    with pytest.raises(ReplayLossError, match=r"cannot recover 1 acknowledged item\(s\): 1 item\(s\) \(ids 45;"):
        ReplayStore(cfg(), tmp_path)
    assert seg.read_bytes() == before and not (tmp_path / "losses.json").exists()  # refused: wrote nothing
    with caplog.at_level(logging.ERROR), ReplayStore(cfg(), tmp_path, accept_loss=True) as s:
        assert _held(s) == [i for c in chunks for i in c if i != 45]  # 99 of 100: every intact record
        assert s.stats()["lost_items"] == 1
    assert any("ids 45;" in r.getMessage() for r in caplog.records)
    record = json.loads((tmp_path / "losses.json").read_text())["losses"]
    assert [(e["kind"], e["ranges"]) for e in record] == [("lost", [[45, 46]])]


def test_a_damaged_record_header_resynchronises_at_the_next_good_record(tmp_path) -> None:
    _log_chunks(tmp_path, n_chunks=4, per_chunk=10)
    seg = segments(tmp_path)[-1]
    offset, _ = _record_offsets(seg)[12]
    _damage(seg, offset + 1, b"\x77\x77\x77")  # the record's length field: its framing is gone
    with pytest.raises(ReplayLossError, match=r"1 item\(s\) \(ids 12;"):
        ReplayStore(cfg(), tmp_path)
    with ReplayStore(cfg(), tmp_path, accept_loss=True) as s:
        assert _held(s) == [i for i in range(40) if i != 12]
        s.insert(tr(1000))  # the log goes on after the repaired segment
    with ReplayStore(cfg(), tmp_path) as s:
        assert len(_held(s)) == 40


def _segmented_store(tmp_path, n: int = 60, close: bool = True) -> dict[int, list[int]]:
    """n items in several small segments; closed (final snapshot) or crashed. Segment number -> ids."""
    s = ReplayStore(cfg(), tmp_path)
    s._log.segment_max_bytes = 1 << 14  # below the config's 1 MiB floor: several segments from few items
    for i in range(n):
        s.insert(tr(i, size=16, seed=i, priority=1.0))
    by_segment: dict[int, list[int]] = {}
    for item_id in _held(s):
        by_segment.setdefault(s._location(item_id).segment, []).append(item_id)
    if close:
        s.close()
    else:
        crash(s)
    assert len(by_segment) >= 4
    return by_segment


@pytest.mark.parametrize("close", [True, False], ids=["after-snapshot", "after-crash"])
def test_a_deleted_segment_is_refused_with_its_exact_ids(tmp_path, close: bool) -> None:
    by_segment = _segmented_store(tmp_path, close=close)
    gone = by_segment[2]
    (tmp_path / "segment-000002.mcap").unlink()
    snapshots = sorted(p.name for p in tmp_path.glob("snapshot-*"))
    with pytest.raises(ReplayLossError) as err:
        ReplayStore(cfg(), tmp_path)
    line = str(err.value)
    assert f"{len(gone)} acknowledged item(s)" in line and f"ids {gone[0]}-{gone[-1]};" in line
    assert "segment-000002.mcap is missing" in line or "segment-000002.mcap missing" in line
    assert sorted(p.name for p in tmp_path.glob("snapshot-*")) == snapshots  # no snapshot sealed the loss
    with ReplayStore(cfg(), tmp_path, accept_loss=True) as s:
        assert _held(s) == [i for i in range(60) if i not in gone]
        s.snapshot()
    with ReplayStore(cfg(), tmp_path) as s:  # recorded: later restarts go on, the record stays
        assert s.stats()["lost_items"] == len(gone)
    assert "--accept-loss" in line and "\n" not in line


def test_an_emptied_last_segment_after_a_snapshot_names_every_id(tmp_path) -> None:
    by_segment = _segmented_store(tmp_path, close=True)
    last = max(by_segment)
    (tmp_path / f"segment-{last:06d}.mcap").write_bytes(b"")
    with pytest.raises(ReplayLossError, match=f"{len(by_segment[last])} acknowledged item.*"
                                              f"ids {by_segment[last][0]}-{by_segment[last][-1]};.*is empty"):
        ReplayStore(cfg(), tmp_path)


def test_an_emptied_last_segment_after_a_crash_is_refused_as_uncounted(tmp_path) -> None:
    by_segment = _segmented_store(tmp_path, close=False)
    last = max(by_segment)
    (tmp_path / f"segment-{last:06d}.mcap").write_bytes(b"")
    with pytest.raises(ReplayLossError, match=f"an uncounted number of items.*segment-{last:06d}.mcap"):
        ReplayStore(cfg(), tmp_path)
    with ReplayStore(cfg(), tmp_path, accept_loss=True) as s:
        assert _held(s) == [i for i in range(60) if i < by_segment[last][0]]
        assert s.insert(tr(500)).item_id >= by_segment[last][0]


def test_zeroed_bytes_in_a_snapshotted_segment_are_found_quarantined_and_never_sampled(tmp_path, caplog) -> None:
    by_segment = _segmented_store(tmp_path, close=True)
    victim = by_segment[2][1]
    with ReplayStore(cfg(), tmp_path) as s:
        loc = s._location(victim)
    _damage(tmp_path / "segment-000002.mcap", loc.data_offset + 40, bytes(min(4096, loc.length - 60)))
    assert cli_main(["replay", "--check", str(tmp_path)]) == 1  # found without a server
    with caplog.at_level(logging.ERROR), ReplayStore(cfg(), tmp_path) as s:  # not scanned at start
        assert victim in _held(s)
        rng = np.random.default_rng(0)
        seen = set()
        for _ in range(8):
            batch = decode_batch_tolerant(bytes(s.sample_encoded(64, rng=rng)))[0]
            assert len(batch.items) == 64  # never a damaged item in a batch
            seen.update(it.item_id for it in batch.items)
            seen.update(it.item_id for it in s.sample(64, rng=rng).items)
        assert victim not in seen and victim not in _held(s)
        stats = s.stats()
        assert stats["quarantined_items"] == 1 and stats["quarantined_ids"] == [victim]
    assert any(f"replay item {victim} quarantined" in r.getMessage() for r in caplog.records)
    assert cli_main(["replay", "--check", str(tmp_path)]) == 0  # recorded in losses.json now
    with ReplayStore(cfg(), tmp_path) as s:
        assert victim not in _held(s) and s.stats()["quarantined_ids"] == [victim]


def test_the_learner_drops_only_the_item_whose_bytes_are_damaged(tmp_path) -> None:
    with ReplayStore(cfg(), tmp_path) as s:
        for i in range(8):
            s.insert(tr(i, seed=i, priority=1.0))
        buf = s.sample_encoded(8, rng=np.random.default_rng(1))
        ids = [it.item_id for it in s.sample(8, rng=np.random.default_rng(1)).items]
    data = bytearray(buf)
    victim = ids[3]
    first = bytes(encode_transition(tr(victim, seed=victim)))[:24]
    at = bytes(data).find(first)  # the start of the transition: zeroing it breaks its protobuf framing
    while at >= 0:
        data[at:at + 24] = bytes(24)
        at = bytes(data).find(first)
    batch, corrupt = decode_batch_tolerant(bytes(data))
    assert [c.item_id for c in corrupt] == [victim] * ids.count(victim)
    assert [it.item_id for it in batch.items] == [i for i in ids if i != victim]
