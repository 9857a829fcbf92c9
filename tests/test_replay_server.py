"""Integration: a real `romannet replay` process on loopback Zenoh, driven by ZenohReplayClient.

Each test picks free ports, runs with multicast scouting off, closes every session, and bounds every
wait with a timeout. Heightmaps are 32x32 ([workspace] resolution_m = 0.014) to keep PNG work small.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from _wire_samples import CRAFTED_PNGS, assert_transitions_equal, transition

from romannet.common import romannet_pb2 as pb
from romannet.common import wire
from romannet.common.replay_client import RateLimitedError, ZenohReplayClient
from romannet.common.wire_messages import PriorityUpdateMsg
from romannet.common.zenoh_session import (
    NoReplyError,
    RemoteError,
    free_port,
    make_config,
    open_session,
    query_one,
)
from romannet.replay.batchcodec import encode_sample_batch_fast, sample_batch_layout

RUN = "test-run"
SIDE_PX = 32
CONFIG_TOML = f"""run_id = "{RUN}"
[workspace]
resolution_m = 0.014
[replay]
min_size_to_sample = 1
samples_per_insert = 0.0  # no learner samples here: unpaced
max_batch_size = 32  # the restart check samples 32 items at once
snapshot_every_s = 0.0
snapshot_every_inserts = 0
top_k = 1000
"""


def _item(step: int, episode: str = "ep-1", **kw: object) -> wire.TransitionMsg:
    kw.setdefault("done", False)
    kw.setdefault("done_reason", "")
    return transition(SIDE_PX, SIDE_PX, seed=step % 5, episode_id=episode, step=step, initial_priority=1.0,
                      **kw)


class Server:
    """A `romannet replay` subprocess on 127.0.0.1:<port> serving <tmp>/store."""

    def __init__(self, tmp: Path, port: int):
        self.tmp, self.port, self.dir = tmp, port, tmp / "store"
        self.config = tmp / "replay.toml"
        self.config.write_text(CONFIG_TOML)
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        cmd = [sys.executable, "-m", "romannet.cli", "replay", "--config", str(self.config), "--dir",
               str(self.dir), "--listen", f"tcp/127.0.0.1:{self.port}"]
        self.log = open(self.tmp / "server.log", "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(cmd, stdout=self.log, stderr=subprocess.STDOUT)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 30) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout_s)
        finally:
            self.log.close()

    def kill(self) -> None:
        """Cleanup after a failed test: no server process outlives its test."""
        if self.proc is not None and self.proc.poll() is None:
            self.stop(signal.SIGKILL)

    def output(self) -> str:
        return (self.tmp / "server.log").read_text(errors="replace")


@pytest.fixture
def server(tmp_path: Path) -> Iterator[Server]:
    srv = Server(tmp_path, free_port())
    srv.start()
    yield srv
    srv.kill()


@pytest.fixture
def client(server: Server) -> Iterator[ZenohReplayClient]:
    with open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{server.port}"])) as session:
        c = ZenohReplayClient(session, RUN, expected_shape=(SIDE_PX, SIDE_PX))
        assert c.wait_until_ready(60), "server did not come up:\n" + server.output()
        yield c


def _ready_client(session, server: Server) -> ZenohReplayClient:
    c = ZenohReplayClient(session, RUN, expected_shape=(SIDE_PX, SIDE_PX))
    assert c.wait_until_ready(60), "server did not come up:\n" + server.output()
    return c


def test_fast_batch_encoding_decodes_like_wire() -> None:
    items = tuple(wire.SampleItem(2**40 + i, 0.25, 0.5, wire.encode_transition(_item(i))) for i in range(3))
    batch = wire.SampleBatchMsg("req-7", items, 99)
    fast = wire.decode_sample_batch(encode_sample_batch_fast(batch))
    slow = wire.decode_sample_batch(wire.encode_sample_batch(batch))
    assert (fast.request_id, fast.buffer_size) == (slow.request_id, slow.buffer_size)
    for a, b in zip(fast.items, slow.items, strict=True):
        assert (a.item_id, a.probability, a.is_weight) == (b.item_id, b.probability, b.is_weight)
        assert_transitions_equal(a.transition, b.transition)
    # The server's layout (holes filled from the log) is byte for byte the same batch.
    buf, offsets = sample_batch_layout("req-7", 99, [(it.item_id, it.probability, it.is_weight,
                                                      len(it.transition)) for it in items])
    for it, off in zip(items, offsets, strict=True):
        buf[off:off + len(it.transition)] = it.transition
    assert bytes(buf) == encode_sample_batch_fast(batch)


def test_client_times_out_cleanly_without_server() -> None:
    with open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{free_port()}"])) as session:
        c = ZenohReplayClient(session, RUN)
        t0 = time.monotonic()
        with pytest.raises(TimeoutError, match="no reply"):
            c.insert(_item(0), timeout_s=1.0)
        with pytest.raises(NoReplyError):
            c.stats(timeout_s=0.5)
        assert time.monotonic() - t0 < 10
        assert not c.wait_until_ready(0.3)


def test_idempotent_insert_fuzz_and_sigterm(server: Server, client: ZenohReplayClient) -> None:
    with pytest.raises(RateLimitedError):  # empty buffer: the rate limiter holds the sample back
        client.sample(1, timeout_s=0.5)
    ack = client.insert(_item(0))
    assert ack.status == "accepted" and ack.item_id is not None
    # The ack was "lost": the actor sends the same transition again.
    again = client.insert(_item(0))
    assert (again.status, again.item_id) == ("duplicate", ack.item_id)
    assert client.stats()["size"] == 1

    rng = np.random.default_rng(0)
    valid = wire.encode_transition(_item(1))
    refused = 0
    accepted: set[int] = {ack.item_id}
    for i in range(300):
        if i % 3 == 0:
            data = rng.bytes(int(rng.integers(0, 2000)))
        elif i % 3 == 1:
            raw = bytearray(valid)
            for j in rng.integers(0, len(raw), int(rng.integers(1, 8))):
                raw[j] ^= 1 << int(rng.integers(8))
            data = bytes(raw)
        else:
            data = valid[: int(rng.integers(0, len(valid)))]
        try:
            fuzzed = client.insert_encoded(data, timeout_s=10)
            if fuzzed.status == "accepted":  # a flip in a harmless spot (e.g. q_value) is a valid transition
                accepted.add(fuzzed.item_id)
        except RemoteError as err:
            refused += 1
            assert err.reason and err.detail
    # Garbage at the other keys: a priority update and a sample request that do not decode.
    client._session.put(client.keys.replay_priorities, b"\xff" * 50)
    with pytest.raises(RemoteError):
        query_one(client._session, client.keys.replay_sample, b"\x00garbage", timeout_s=10)
    client.update_priorities(PriorityUpdateMsg((ack.item_id, 10**9), (3.0, 1.0)))  # unknown id: ignored

    # Still serving: a valid insert is acknowledged and sampling works.
    last = client.insert(_item(2))
    assert last.status == "accepted"
    accepted.add(last.item_id)
    batch = client.sample(4, timeout_s=10)
    assert len(batch.items) == 4 and batch.buffer_size >= 2
    raw = client.sample_encoded(3, timeout_s=10)  # the undecoded reply, as the learner's tolerant decoder takes it
    assert len(wire.decode_sample_batch(raw).items) == 3
    stats = _wait_for(lambda: client.stats(), lambda s: "priorities" in s["server"]["rejected"])
    rejected = stats["server"]["rejected"]
    assert sum(rejected["insert"].values()) == refused >= 200
    assert rejected["sample"] and rejected["priorities"]
    assert stats["size"] == len(accepted)

    assert server.stop(signal.SIGTERM) == 0, server.output()
    assert list(server.dir.glob("snapshot-*")), "no snapshot written at shutdown"


def test_crafted_png_behind_valid_crcs_is_refused_and_not_stored(server: Server,
                                                                 client: ZenohReplayClient) -> None:
    sent = 0
    for craft, make in sorted(CRAFTED_PNGS.items()):
        for field in ("color_before_png", "depth_after_png"):
            m = pb.Transition.FromString(wire.encode_transition(_item(sent)))
            setattr(m, field, make(getattr(m, field)))
            with pytest.raises(RemoteError) as err:
                client.insert_encoded(m.SerializeToString(), timeout_s=10)
            assert err.value.reason == "bad_image", (craft, err.value)
            assert f"{field} PNG is corrupt" in err.value.detail, (craft, err.value.detail)
            sent += 1
    stats = client.stats()
    assert stats["size"] == 0
    assert stats["server"]["rejected"]["insert"] == {"bad_image": sent}
    assert client.insert(_item(100)).status == "accepted"  # still serving
    assert client.stats()["size"] == 1
    assert server.stop(signal.SIGTERM) == 0, server.output()


def _wait_for(get, ok, timeout_s: float = 10.0):
    deadline = time.monotonic() + timeout_s
    while True:
        value = get()
        if ok(value) or time.monotonic() > deadline:
            return value
        time.sleep(0.05)


def test_sigkill_mid_stream_loses_no_acknowledged_insert(tmp_path: Path, request: pytest.FixtureRequest) -> None:
    srv = Server(tmp_path, free_port())
    request.addfinalizer(srv.kill)
    endpoint = [f"tcp/127.0.0.1:{srv.port}"]
    with open_session(make_config(listen=[], connect=endpoint)) as session:
        # Phase 1: a few items with learner priorities, then a clean stop (snapshot).
        srv.start()
        c = _ready_client(session, srv)
        first = [c.insert(_item(i, "ep-a")) for i in range(10)]
        ids = tuple(a.item_id for a in first)
        priorities = tuple(float(5 + i) for i in range(10))
        c.update_priorities(PriorityUpdateMsg(ids, priorities))
        _wait_for(lambda: c.stats(), lambda s: s["server"]["handled"]["priorities"] >= 1)
        assert srv.stop(signal.SIGTERM) == 0, srv.output()

        # Phase 2: restart, stream inserts, SIGKILL while acknowledged inserts are flowing.
        srv.start()
        c = _ready_client(session, srv)
        acked: dict[tuple[str, int], int] = {}
        stop = threading.Event()

        def stream() -> None:
            step = 0
            while not stop.is_set():
                try:
                    ack = c.insert(_item(step, "ep-b"), timeout_s=2.0)
                except (TimeoutError, RemoteError):
                    return  # the server is gone
                acked[("ep-b", step)] = ack.item_id
                step += 1

        streamer = threading.Thread(target=stream)
        streamer.start()
        _wait_for(lambda: len(acked), lambda n: n >= 40, timeout_s=60)
        srv.stop(signal.SIGKILL)
        stop.set()
        streamer.join(30)
        assert len(acked) >= 40

        # Phase 3: restart on the same directory: every acknowledged transition is there.
        srv.start()
        c = _ready_client(session, srv)
        stats = c.stats()
        expected = len(first) + len(acked)
        assert expected <= stats["size"] <= expected + 1  # + the one in flight, durable but not acked
        for (episode, step), item_id in acked.items():
            again = c.insert(_item(step, episode))
            assert (again.status, again.item_id) == ("duplicate", item_id), (episode, step)
        known = set(ids) | set(acked.values())
        batch = c.sample(32, timeout_s=10)
        assert {item.item_id for item in batch.items} <= known | {max(known) + 1}
        # Priorities: phase 1's come from the last snapshot, phase 2's items kept their initial priority.
        prio = _priorities(c.stats())
        for item_id, p in zip(ids, priorities, strict=True):
            assert prio[item_id] == pytest.approx(p)
        for item_id in acked.values():
            assert prio[item_id] == pytest.approx(1.0)
        assert srv.stop(signal.SIGTERM) == 0, srv.output()


def _priorities(stats: dict) -> dict[int, float] | None:
    """{item_id: priority} from the stats' top-k list (top_k = 1000 covers every item here)."""
    return {int(e["item_id"]): float(e["priority"]) for e in stats["top_priorities"]}
