"""Replay durability: acked inserts survive a crash; torn, truncated and corrupt log tails; snapshots."""

from __future__ import annotations

import logging
import struct

import numpy as np
import pytest
from _replay_helpers import cfg, crash, segments, tr
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory

from romannet.common.wire import PriorityUpdateMsg, decode_transition
from romannet.replay.losses import ReplayLossError
from romannet.replay.store import ReplayStore


def _held(store: ReplayStore) -> dict[int, float]:
    ids, prios = store._sampler.items()
    return dict(zip(ids.tolist(), prios.tolist(), strict=True))


def _last_chunk_offset(path) -> int:
    """Offset of the last Chunk record (opcode 0x06) of a segment, found by walking its records."""
    data = path.read_bytes()
    pos, last = 8, None
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        if opcode == 0x06:
            last = pos
        pos += 9 + length
    assert last is not None
    return last


def _populate(tmp_path, n_before: int = 6, n_after: int = 4) -> tuple[dict[int, float], list[int]]:
    """Insert, snapshot, update priorities (lost: after the snapshot), insert more, crash."""
    s = ReplayStore(cfg(), tmp_path)
    acked = [s.insert(tr(i, priority=float(i + 1))).item_id for i in range(n_before)]
    s.update_priorities(PriorityUpdateMsg((0,), (50.0,)))
    s.snapshot()
    s.update_priorities(PriorityUpdateMsg((1,), (99.0,)))  # after the last snapshot: not durable
    acked += [s.insert(tr(100 + i)).item_id for i in range(n_after)]  # logged with the max then: 99
    crash(s)
    # Item 1 falls back to its snapshot priority; the tail items keep the priority they were logged with.
    expected = {i: float(i + 1) for i in range(n_before)} | {0: 50.0} | {i: 99.0 for i in acked[n_before:]}
    return expected, acked


def test_crash_keeps_every_acknowledged_item_with_snapshot_plus_log_priorities(tmp_path, caplog) -> None:
    expected, acked = _populate(tmp_path)
    with caplog.at_level(logging.WARNING):
        s = ReplayStore(cfg(), tmp_path)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert _held(s) == expected
    assert s.recovered.tail_items == 4 and s.recovered.snapshot is not None
    for item_id in acked:  # the bytes are there and decode
        assert decode_transition(s._log.read(s._location(item_id))).step in (*range(6), *range(100, 104))
    assert s.insert(tr(101)).status == "duplicate"  # idempotency survives the restart
    assert s.insert(tr(200)).item_id == acked[-1] + 1
    s.close()


def test_torn_final_chunk_is_dropped_with_a_warning(tmp_path, caplog) -> None:
    expected, _ = _populate(tmp_path)
    seg = segments(tmp_path)[-1]
    whole = seg.read_bytes()
    start = _last_chunk_offset(seg)
    seg.write_bytes(whole + whole[start:start + (len(whole) - start) // 2])  # a chunk cut by kill -9
    with caplog.at_level(logging.WARNING):
        s = ReplayStore(cfg(), tmp_path)
    assert _held(s) == expected  # nothing acknowledged was lost
    warning = " ".join(r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    assert f"dropped {(len(whole) - start) // 2} byte(s)" in warning and "1 transition record" in warning
    s.close()
    assert list(tmp_path.glob("*.bad"))  # the dropped bytes are kept for forensics


def test_truncated_log_recovers_up_to_the_last_whole_chunk(tmp_path, caplog) -> None:
    expected, acked = _populate(tmp_path)
    seg = segments(tmp_path)[-1]
    whole = seg.read_bytes()
    start = _last_chunk_offset(seg)  # the last insert's chunk (one insert per chunk here)
    seg.write_bytes(whole[:start + 100])
    with caplog.at_level(logging.WARNING):
        s = ReplayStore(cfg(), tmp_path)
    del expected[acked[-1]]
    assert _held(s) == expected
    assert any(f"dropped {100} byte(s)" in r.getMessage() for r in caplog.records)
    s.close()


def test_bit_flipped_tail_record_is_a_named_loss_the_operator_must_accept(tmp_path, caplog) -> None:
    expected, acked = _populate(tmp_path)
    seg = segments(tmp_path)[-1]
    data = bytearray(seg.read_bytes())
    start = _last_chunk_offset(seg)
    data[start + 200] ^= 0x10  # inside the last record's transition bytes
    seg.write_bytes(bytes(data))
    with pytest.raises(ReplayLossError, match=f"ids {acked[-1]};.*fails its checksum.*--accept-loss"):
        ReplayStore(cfg(), tmp_path)
    assert seg.read_bytes() == bytes(data)  # refused: nothing was repaired or written
    with caplog.at_level(logging.ERROR):
        s = ReplayStore(cfg(), tmp_path, accept_loss=True)
    del expected[acked[-1]]
    assert _held(s) == expected
    assert any(f"ids {acked[-1]};" in r.getMessage() for r in caplog.records if r.levelno == logging.ERROR)
    assert s.stats()["lost_items"] == 1
    s.close()
    with ReplayStore(cfg(), tmp_path) as again:  # accepted and recorded: a second restart goes on
        assert _held(again) == expected


def test_leftover_tmp_and_corrupt_newest_snapshot_are_ignored(tmp_path, caplog) -> None:
    s = ReplayStore(cfg(), tmp_path)
    for i in range(3):
        s.insert(tr(i, priority=1.0))
    s.snapshot()
    s.update_priorities(PriorityUpdateMsg((2,), (8.0,)))
    s.insert(tr(3, priority=2.0))
    newest = s.snapshot()
    crash(s)
    (tmp_path / "snapshot-000000000099.npz.tmp").write_bytes(b"half a snapshot")
    newest.write_bytes(newest.read_bytes()[:50])  # as if the disk lost it
    with caplog.at_level(logging.WARNING):
        s = ReplayStore(cfg(), tmp_path)
    assert _held(s) == {0: 1.0, 1: 1.0, 2: 1.0, 3: 2.0}  # the older snapshot + the log
    assert any("unreadable snapshot" in r.getMessage() for r in caplog.records)
    assert not list(tmp_path.glob("*.tmp"))
    s.close()


def test_recovery_without_any_snapshot_replays_the_whole_log(tmp_path) -> None:
    s = ReplayStore(cfg(), tmp_path)
    for i in range(5):
        s.insert(tr(i, priority=float(i)))
    crash(s)
    with ReplayStore(cfg(capacity_items=3), tmp_path) as s:  # a smaller capacity applies on recovery
        assert _held(s) == {2: 2.0, 3: 3.0, 4: 4.0}


def test_segments_rotate_are_standard_mcap_and_evicted_ones_are_reclaimed(tmp_path) -> None:
    c = cfg(capacity_items=40, segment_max_bytes=1 << 20)
    s = ReplayStore(c, tmp_path)
    for i in range(120):  # ~16 kB each: several 1 MiB segments
        s.insert(tr(i, size=64, seed=i, priority=1.0))
    assert len(segments(tmp_path)) >= 2
    crash(s)
    unfinished = segments(tmp_path)[-1]
    steps = []
    with unfinished.open("rb") as fh, pytest.raises(EndOfFile):  # no footer yet: read to the end
        for record in StreamReader(fh, validate_crcs=True).records:
            if isinstance(record, Message):
                steps.append(decode_transition(record.data).step)
    assert steps and steps[-1] == 119
    s = ReplayStore(c, tmp_path)
    first_before = segments(tmp_path)[0]
    s.snapshot()  # records the eviction watermark, then deletes segments below it
    assert not first_before.exists()
    held = _held(s)
    assert sorted(held) == list(range(80, 120))
    s.close()
    for seg in segments(tmp_path):  # every segment is a complete, decodable MCAP file now
        with seg.open("rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _, channel, message, decoded in reader.iter_decoded_messages():
                assert channel.topic == "/replay/transitions" and decoded.initial_priority == 1.0
                assert message.sequence == decoded.step  # item id mod 2^32; here id == step
    with ReplayStore(c, tmp_path) as s:
        assert sorted(_held(s)) == list(range(80, 120))
        batch = s.sample(4, rng=np.random.default_rng(0))
        assert all(80 <= it.item_id < 120 for it in batch.items)


def test_concurrent_inserts_are_all_durable(tmp_path) -> None:
    import threading

    s = ReplayStore(cfg(), tmp_path)
    acks = []

    def actor(a: int) -> None:
        acks.extend(s.insert(tr(i, actor=f"sim-{a}")) for i in range(10))

    threads = [threading.Thread(target=actor, args=(a,)) for a in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    crash(s)
    with ReplayStore(cfg(), tmp_path) as s:
        assert sorted(_held(s)) == sorted(a.item_id for a in acks) == list(range(40))
