"""Size limits before the bytes are held (issue 31 point 2): the Zenoh message cap each service sets, and
2,000 malformed, random and oversized messages at a real `romannet replay` process over loopback Zenoh.

The fuzz here sends one 100 MB and one 250 MB message among the 2,000; `romannet bench fuzz` adds the
500 MB and 1 GB ones (seconds of loopback traffic and 2 GB in the sending process each).
"""

from __future__ import annotations

import logging
import threading
import time

import pytest
import zenoh

from romannet.bench.fuzz import FuzzPlan, fuzz_transition, run_fuzz
from romannet.common import wire
from romannet.common.replay_client import ZenohReplayClient, refused_for_good
from romannet.common.wire_messages import InsertAckMsg
from romannet.common.zenoh_limits import (
    FLEET_MAX_MESSAGE_BYTES,
    learner_receive_limit,
    limit_messages,
    message_limit,
    replay_receive_limit,
)
from romannet.common.zenoh_session import (
    RemoteError,
    free_port,
    make_config,
    open_session,
    parse_error,
    wait_for_liveliness,
)
from romannet.replay.server import ReplayServer, ServerLimits

MIB = 1 << 20


def test_every_shipped_config_caps_messages() -> None:
    assert message_limit(make_config()) == FLEET_MAX_MESSAGE_BYTES  # the embedded default
    for name in ("deploy/zenoh-local.json5", "deploy/zenoh/router.json5", "deploy/zenoh/replay.json5",
                 "deploy/zenoh/secure/actor-0.json5"):
        assert message_limit(zenoh.Config.from_file(name)) == FLEET_MAX_MESSAGE_BYTES, name


def test_a_service_lowers_the_cap_to_what_its_role_receives(caplog: pytest.LogCaptureFixture) -> None:
    config = make_config()
    assert limit_messages(config, replay_receive_limit(16 * MIB), "replay server") == 17 * MIB
    assert message_limit(config) == 17 * MIB
    assert learner_receive_limit(4, 16 * MIB) == 65 * MIB
    assert learner_receive_limit(256, 16 * MIB) == FLEET_MAX_MESSAGE_BYTES
    # A file's lower cap is the operator's choice: kept, with one line saying what it will drop.
    with caplog.at_level(logging.WARNING):
        assert limit_messages(config, 65 * MIB, "learner") == 17 * MIB
    assert message_limit(config) == 17 * MIB
    assert len(caplog.records) == 1 and "below the 68157440 bytes this learner may need" in caplog.text


def test_fuzz_2000_messages_with_100_mb_and_250_mb_keeps_memory_flat(tmp_path) -> None:
    result = run_fuzz(FuzzPlan(messages=2000, big_mb=(100, 250)), work_dir=tmp_path)
    assert result["messages"] == 2000
    assert result["big_replied"] == 0  # dropped by Zenoh at the server's cap: never held whole
    assert result["refused_by_reason"]["oversized"] >= 10  # just over max_item_bytes: refused at once
    assert {"undecodable", "bad_image", "wrong_actor"} <= set(result["refused_by_reason"])
    assert result["peak_ratio"] <= 2.0, result
    assert result["still_answering"] and result["stored"] == result["expected_stored"], result
    assert result["server_exit_code"] == 0 and result["server_tracebacks"] == 0, result
    # Throttled: one line per refusal kind for the first few, not one per message.
    assert result["server_log_lines"] < 200, result
    assert result["ok"]


class _SlowStore:
    """What ReplayServer needs of a store; insert waits for `release`, so later messages stay queued."""

    def __init__(self) -> None:
        self.release = threading.Event()

    def insert(self, msg, encoded=None, timeout_s=10.0) -> InsertAckMsg:
        self.release.wait(30)
        return InsertAckMsg(msg.actor_id, msg.episode_id, msg.step, "accepted", 1)

    def record_rejection(self, reason: str) -> None:
        pass

    def stats(self) -> dict:
        return {"size": 0}


def test_queued_bytes_are_bounded_and_an_oversized_insert_is_refused_before_queueing() -> None:
    port = free_port()
    store = _SlowStore()
    limits = ServerLimits(insert_workers=1, max_insert_bytes=2 * MIB, max_queued_bytes=int(2.5 * MIB))
    with open_session(make_config(listen=[f"tcp/127.0.0.1:{port}"])) as server_session, \
            open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as session, \
            ReplayServer(store, server_session, "lim", limits) as server:
        key = server.keys.replay_insert("fuzz-0")
        assert wait_for_liveliness(session, server.keys.replay_alive, 30)
        # One valid insert holds the only worker; two 1 MiB messages queue behind it (2 MiB + its bytes).
        held = session.get(key, payload=wire.encode_transition(fuzz_transition(0)), timeout=30)
        queued = [session.get(key, payload=bytes(MIB), timeout=30) for _ in range(2)]
        deadline = time.monotonic() + 30
        while server.stats()["server"]["queued"]["insert"] < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        # The third would pass 2.5 MiB queued: refused at once, as is one over max_insert_bytes.
        third = next(iter(session.get(key, payload=bytes(MIB), timeout=5)))
        assert parse_error(third.err.payload.to_bytes())[0] == "overloaded"
        big = next(iter(session.get(key, payload=bytes(2 * MIB + 1), timeout=5)))
        assert parse_error(big.err.payload.to_bytes()) == (
            "oversized", f"transition is {2 * MIB + 1} bytes; this server accepts at most {2 * MIB}")
        store.release.set()
        assert next(iter(held)).ok is not None
        for replies in queued:  # taken once the worker was free, then refused as garbage
            assert parse_error(next(iter(replies)).err.payload.to_bytes())[0] == "undecodable"
        deadline = time.monotonic() + 30  # a worker releases a message's bytes just after its reply
        while server.stats()["server"]["queued_bytes"] and time.monotonic() < deadline:
            time.sleep(0.02)
        assert server.stats()["server"]["queued_bytes"] == 0


def test_a_client_does_not_send_a_transition_over_the_servers_item_limit() -> None:
    """Over the server's Zenoh cap it would be dropped unanswered and resent for ever: refused here, with a
    reason the actor's sender files under spool/rejected/ (refused_for_good)."""
    data = wire.encode_transition(fuzz_transition(0))
    with open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{free_port()}"])) as session:
        client = ZenohReplayClient(session, "lim", actor_id="fuzz-0", max_insert_bytes=len(data) - 1)
        started = time.monotonic()
        with pytest.raises(RemoteError) as err:
            client.insert_encoded(data, timeout_s=30)
    assert time.monotonic() - started < 1.0  # not sent: nothing waited for a reply
    assert err.value.reason == "oversized" and refused_for_good(err.value.reason)
    assert f"transition is {len(data)} bytes" in err.value.detail
