"""query_one over real loopback Zenoh sessions: a late answer is "no reply", a refusal keeps its token."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from romannet.common.replay_client import INSERT_REFUSALS, refused_for_good
from romannet.common.zenoh_session import (
    NoReplyError,
    RemoteError,
    format_error,
    free_port,
    make_config,
    open_session,
    query_one,
)
from romannet.replay.rejections import _DECODE_REASONS, classify_decode_error


@pytest.fixture
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    port = free_port()
    with open_session(make_config(listen=[f"tcp/127.0.0.1:{port}"])) as server, \
            open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as client:
        yield server, client


def test_an_answer_after_the_timeout_is_no_reply_not_a_refusal(sessions: tuple[zenoh.Session, zenoh.Session]) -> None:
    # Zenoh itself ends an unanswered query with an error reply ("Timeout"): read as a refusal, an actor would
    # drop the transition for good, although the server may still store it or be merely slow.
    server, client = sessions
    answered = threading.Event()

    def slow(query: zenoh.Query) -> None:
        time.sleep(1.5)
        answered.set()

    with server.declare_queryable("t/slow", slow):
        time.sleep(0.5)
        with pytest.raises(NoReplyError):
            query_one(client, "t/slow", b"x", timeout_s=0.5)
        assert answered.wait(5.0)


def test_a_refusal_keeps_its_reason_token(sessions: tuple[zenoh.Session, zenoh.Session]) -> None:
    server, client = sessions

    def refuse(query: zenoh.Query) -> None:
        query.reply_err(format_error("oversized", "transition is 9 bytes; at most 8"))

    with server.declare_queryable("t/refuse", refuse):
        time.sleep(0.5)
        with pytest.raises(RemoteError) as err:
            query_one(client, "t/refuse", b"x", timeout_s=5.0)
    assert (err.value.reason, err.value.detail) == ("oversized", "transition is 9 bytes; at most 8")
    assert refused_for_good(err.value.reason)


def test_every_bad_input_token_of_the_server_is_final_and_nothing_else() -> None:
    tokens = {reason for _, reason in _DECODE_REASONS} | {classify_decode_error("something else")}
    assert tokens <= INSERT_REFUSALS
    for transient in ("rate_limited", "shutting_down", "overloaded", "internal", "error"):
        assert not refused_for_good(transient)


def test_free_ports_lie_below_the_ephemeral_range_and_never_repeat() -> None:
    # A port from the ephemeral range can be taken by any outgoing connection before the service listens on
    # it (a CI run lost a replay server that way); one handed out twice would collide within the process.
    low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    ports = [free_port() for _ in range(50)]
    assert len(set(ports)) == 50
    if low > 11000:
        assert all(10000 <= port < low for port in ports)
    with open_session(make_config(listen=[f"tcp/127.0.0.1:{ports[0]}"], connect=[])):
        pass  # a port handed out can be listened on
