"""The actor's on-disk spool and sender: bound and pause, crash safety (resend after restart, no duplicates),
rejected transitions, a flaky replay server (TimeoutError for a while)."""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path

import pytest
from _replay_helpers import cfg as replay_cfg
from _replay_helpers import tr

from romannet.actor.sender import Sender, SenderStats, item_key, spool_pause
from romannet.actor.spool import Spool
from romannet.common.replay_client import RateLimitedError
from romannet.common.wire import InsertAckMsg, TransitionMsg, decode_transition, encode_transition
from romannet.common.zenoh_session import NoReplyError, RemoteError
from romannet.replay.inprocess import InProcessReplayClient
from romannet.replay.store import ReplayStore

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def store(tmp_path: Path):
    s = ReplayStore(replay_cfg(fsync=False), tmp_path / "replay")
    yield s
    s.close()


def _fill(spool: Spool, n: int, episode: str = "ep000000", size: int = 8) -> list[bytes]:
    items = [encode_transition(tr(step, episode=episode, actor="a0", size=size)) for step in range(n)]
    for data in items:
        spool.put(data)
    return items


class FlakyClient:
    """Raises NoReplyError (a TimeoutError) for the first `failures` inserts, then delegates."""

    def __init__(self, inner: InProcessReplayClient, failures: int):
        self.inner, self.failures, self.calls = inner, failures, 0
        self.lock = threading.Lock()

    def insert(self, transition: TransitionMsg, timeout_s: float = 10.0) -> InsertAckMsg:
        with self.lock:
            self.calls += 1
            if self.calls <= self.failures:
                raise NoReplyError("no reply (simulated outage)")
        return self.inner.insert(transition, timeout_s)

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> InsertAckMsg:
        return self.insert(decode_transition(data), timeout_s)


class DownClient:
    """A replay server that never answers."""

    def insert(self, transition: TransitionMsg, timeout_s: float = 10.0) -> InsertAckMsg:
        raise NoReplyError("no reply (server down)")

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> InsertAckMsg:
        raise NoReplyError("no reply (server down)")


def _keys(store: ReplayStore) -> set[tuple[str, str, int]]:
    return set(store._by_key)


def test_put_read_remove_and_bound(tmp_path: Path) -> None:
    spool = Spool(tmp_path / "spool", max_items=3, max_bytes=1 << 30, fsync=False)
    items = _fill(spool, 3)
    assert spool.items == 3 and spool.bytes == sum(map(len, items))
    assert spool.full() and not spool.wait_for_room(0.05)
    oldest = spool.wait_for_item(0.0)
    assert oldest == 0 and spool.read(oldest) == items[0]
    assert item_key(items[0]) == ("a0", "ep000000", 0)
    spool.remove(oldest)
    assert not spool.full() and spool.wait_for_room(0.01) and spool.items == 2
    # The byte bound counts too.
    small = Spool(tmp_path / "small", max_items=100, max_bytes=len(items[0]) + 1, fsync=False)
    small.put(items[0])
    assert not small.full()
    small.put(items[1])
    assert small.full()


def test_pause_resumes_when_acks_flow(tmp_path: Path, store: ReplayStore) -> None:
    """A full spool blocks the producer until the sender drains it (the actor's pause)."""
    spool = Spool(tmp_path / "spool", max_items=2, max_bytes=1 << 30, fsync=False)
    _fill(spool, 2)
    assert not spool.wait_for_room(0.05)
    sender = Sender(spool, FlakyClient(InProcessReplayClient(store), failures=2), insert_timeout_s=1.0,
                    backoff_initial_s=0.05, backoff_max_s=0.1).start()
    try:
        assert spool.wait_for_room(10.0)
        assert spool.wait_until_empty(10.0)
    finally:
        sender.stop(flush_s=1.0)
    stats = sender.stats()
    assert stats.acked == 2 and stats.failures == 2 and stats.reachable and stats.sent == 4
    assert _keys(store) == {("a0", "ep000000", 0), ("a0", "ep000000", 1)}


def test_unacked_items_are_resent_after_restart(tmp_path: Path, store: ReplayStore) -> None:
    directory = tmp_path / "spool"
    spool = Spool(directory, max_items=100, max_bytes=1 << 30)  # fsync on: the real thing
    _fill(spool, 5)
    down = Sender(spool, DownClient(), insert_timeout_s=0.1, backoff_initial_s=0.01, backoff_max_s=0.02).start()
    time.sleep(0.1)
    assert not down.stop(flush_s=0.1)  # nothing acknowledged: all 5 stay on disk
    assert spool.items == 5 and down.stats().acked == 0 and not down.stats().reachable
    # One of them reached the server but its ack was lost (and the process died before removing it);
    # a half-written item of the crash is lying in tmp/.
    store.insert(tr(2, episode="ep000000", actor="a0"))
    (directory / "tmp" / "000000000099.tmp").write_bytes(b"half")

    restarted = Spool(directory, max_items=100, max_bytes=1 << 30)
    assert restarted.recovered == 5 and not list((directory / "tmp").iterdir())
    next_seq = _fill(restarted, 1, episode="ep000001")  # new items go after the recovered ones
    assert len(next_seq) == 1 and restarted.items == 6
    sender = Sender(restarted, InProcessReplayClient(store), insert_timeout_s=1.0, backoff_initial_s=0.01).start()
    try:
        assert restarted.wait_until_empty(10.0)
    finally:
        assert sender.stop(flush_s=1.0)
    stats = sender.stats()
    assert stats.acked == 6 and stats.accepted == 5 and stats.duplicates == 1
    assert _keys(store) == {("a0", "ep000000", s) for s in range(5)} | {("a0", "ep000001", 0)}
    assert store.stats()["size"] == 6
    assert not list(directory.glob("*.pb"))


def test_rejected_items_move_aside_and_are_not_resent(tmp_path: Path) -> None:
    tiny = ReplayStore(replay_cfg(fsync=False, max_item_bytes=1024), tmp_path / "replay")
    try:
        spool = Spool(tmp_path / "spool", max_items=10, max_bytes=1 << 30, fsync=False)
        assert min(map(len, _fill(spool, 2, size=32))) > 1024  # random pixels: PNGs barely compress
        sender = Sender(spool, InProcessReplayClient(tiny), insert_timeout_s=1.0).start()
        assert spool.wait_until_empty(10.0)
        sender.stop(flush_s=0.5)
    finally:
        tiny.close()
    stats = sender.stats()
    assert stats.rejected == 2 and stats.acked == 0 and stats.sent == 2 and spool.rejected == 2
    notes = sorted((tmp_path / "spool" / "rejected").glob("*.json"))
    assert len(notes) == 2 and len(list((tmp_path / "spool" / "rejected").glob("*.pb"))) == 2
    note = json.loads(notes[0].read_text())
    assert "max_item_bytes" in note["reason"] and note["key"].startswith("a0/ep000000/")
    # A new spool on the directory does not pick the rejected items up again.
    assert Spool(tmp_path / "spool", max_items=10, max_bytes=1 << 30).recovered == 0


class ErrorReplyClient:
    """insert_encoded answers with a server error reply: `reason` for the first `times` calls, then acks."""

    def __init__(self, reason: str, times: int):
        self.reason, self.times, self.calls = reason, times, 0

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> InsertAckMsg:
        self.calls += 1
        if self.calls <= self.times:
            raise RemoteError("romannet/@v1/x/replay/insert", self.reason, "simulated")
        actor, episode, step = item_key(data)
        return InsertAckMsg(actor, episode, step, "accepted", item_id=self.calls)

    def insert(self, transition: TransitionMsg, timeout_s: float = 10.0) -> InsertAckMsg:
        raise AssertionError("the sender sends the spool's bytes with insert_encoded")


# Only the server's bad-input tokens are final; a queue that is full, a crash in a handler, an error token
# this client does not know (e.g. Zenoh's own) must never cost an acknowledged-to-be transition.
@pytest.mark.parametrize(("reason", "rejected"), [("shutting_down", 0), ("overloaded", 0), ("internal", 0),
                                                   ("error", 0), ("undecodable", 1), ("oversized", 1),
                                                   ("wrong_actor", 1)])
def test_error_replies_transient_or_permanent(tmp_path: Path, reason: str, rejected: int) -> None:
    spool = Spool(tmp_path / "spool", max_items=10, max_bytes=1 << 30, fsync=False)
    _fill(spool, 1)
    client = ErrorReplyClient(reason, times=2)
    sender = Sender(spool, client, insert_timeout_s=1.0, backoff_initial_s=0.01, backoff_max_s=0.02).start()
    assert spool.wait_until_empty(10.0)
    sender.stop(flush_s=0.5)
    stats = sender.stats()
    assert stats.rejected == rejected and stats.acked == 1 - rejected
    assert client.calls == (3 if rejected == 0 else 1)


class PacingClient(ErrorReplyClient):
    """A live server whose rate limiter holds the first `times` inserts back (the learner lags)."""

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> InsertAckMsg:
        if self.calls < self.times:
            self.calls += 1
            raise RateLimitedError("romannet/@v1/x/replay/insert", "rate_limited", "held for 0.1 s")
        return super().insert_encoded(data, timeout_s)


def test_rate_limited_inserts_are_pacing_not_an_outage(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A held-back insert keeps the server reachable, is resent without a growing backoff (10 s here would
    show) and logs one INFO line, not a warning per insert."""
    spool = Spool(tmp_path / "spool", max_items=10, max_bytes=1 << 30, fsync=False)
    _fill(spool, 2)
    client = PacingClient("rate_limited", times=4)
    sender = Sender(spool, client, insert_timeout_s=1.0, backoff_initial_s=10.0, backoff_max_s=10.0)
    with caplog.at_level(logging.DEBUG, logger="romannet.actor.sender"):
        sender.start()
        assert spool.wait_until_empty(5.0)  # under the 10 s backoff a failure would have cost
        sender.stop(flush_s=0.5)
    stats = sender.stats()
    assert stats.paced == 4 and stats.failures == 0 and stats.acked == 2 and stats.sent == 6
    assert stats.reachable and stats.pacing and stats.last_error == ""  # pacing lasts until a failure
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    told = [r for r in caplog.records if r.levelno == logging.INFO and "paces this actor" in r.getMessage()]
    assert len(told) == 1


def test_pacing_reply_ends_an_outage(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """No reply, then a rate-limited reply: the server answered, so it is reachable again."""
    spool = Spool(tmp_path / "spool", max_items=10, max_bytes=1 << 30, fsync=False)
    _fill(spool, 1)

    class DownThenPacing(PacingClient):
        def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> InsertAckMsg:
            self.outage = getattr(self, "outage", 0) + 1
            if self.outage == 1:
                raise NoReplyError("no reply (simulated outage)")
            return super().insert_encoded(data, timeout_s)

    sender = Sender(spool, DownThenPacing("rate_limited", times=1), insert_timeout_s=1.0,
                    backoff_initial_s=0.01, backoff_max_s=0.02)
    with caplog.at_level(logging.INFO, logger="romannet.actor.sender"):
        sender.start()
        assert spool.wait_until_empty(5.0)
        sender.stop(flush_s=0.5)
    stats = sender.stats()
    assert stats.failures == 1 and stats.paced == 1 and stats.acked == 1 and stats.reachable
    messages = [r.getMessage() for r in caplog.records]
    assert sum("unreachable" in m for m in messages) == 1 and sum("reachable again" in m for m in messages) == 1


def test_spool_pause_kinds() -> None:
    """A full spool is an outage once a request failed, pacing after the rate limiter answered, else waiting."""
    full = "spool full: 2 transitions"
    assert spool_pause(SenderStats(), full) == ("waiting", f"waiting for the replay server to acknowledge; {full}")
    kind, reason = spool_pause(SenderStats(pacing=True), full)
    assert kind == "paced" and reason.startswith("paced by the learner") and reason.endswith(full)
    kind, reason = spool_pause(SenderStats(pacing=False, reachable=False, last_error="NoReplyError: x"), full)
    assert kind == "outage" and "is the replay server reachable? last send error: NoReplyError: x" in reason
