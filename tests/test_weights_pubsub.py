"""WeightsPublisher (learner) -> ZenohWeightsSource (actor) over real Zenoh sessions on loopback.

Two sessions per test (the learner's listens on a free port, the actor's connects), multicast scouting
off, every session closed by its `with`, every wait bounded.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import pytest
import torch
import zenoh

from romannet.common import wire
from romannet.common.config import ModelConfig
from romannet.common.interfaces import WeightsSource
from romannet.common.keys import RunKeys
from romannet.common.model import RoManNet, load_tensors, state_dict_to_tensors, validate_tensors
from romannet.common.weights_client import ZenohWeightsSource
from romannet.common.weightscodec import make_weights
from romannet.common.wire_messages import WeightsAnnouncementMsg
from romannet.common.zenoh_session import free_port, make_config, open_session
from romannet.learner.publisher import WeightsPublisher

RUN = "wtest"
SMALL = ModelConfig(channels=4, residual_blocks=1)


@contextmanager
def two_sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    port = free_port()
    with open_session(make_config(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as learner:
        with open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as actor:
            yield learner, actor


def wait_for(fn: Callable[[], Any], timeout_s: float = 15.0) -> Any:
    """Poll fn until it returns something other than None (or fail after timeout_s)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = fn()
        if value is not None:
            return value
        time.sleep(0.02)
    raise AssertionError(f"nothing within {timeout_s} s")


def tensors(seed: int) -> dict[str, torch.Tensor]:
    torch.manual_seed(seed)
    return {"w": torch.randn(16), "b": torch.randn(2, 3)}


def wait_linked(learner: zenoh.Session, actor: zenoh.Session, timeout_s: float = 10.0) -> None:
    """Until a query from the actor reaches the learner's session. Declarations travel in order on the
    link, so the actor's subscribers declared before this call are known to the learner afterwards."""
    key = f"{RunKeys(RUN).root}/test/ping"
    q = learner.declare_queryable(key, lambda query: query.reply(key, b"pong"))
    try:
        wait_for(lambda: True if any(r.ok is not None for r in actor.get(key, timeout=1.0)) else None,
                 timeout_s)
    finally:
        q.undeclare()


def test_versions_only_increase_and_actor_gets_latest() -> None:
    with two_sessions() as (ls, acs), WeightsPublisher(ls, RUN) as pub:
        pub.publish_weights(1, tensors(1))
        with ZenohWeightsSource(acs, RUN, fetch_timeout_s=5) as src:
            # Started after v1 was announced and no learner liveliness token here: the source learns of
            # weights from the next announcements. Several in quick succession:
            wait_linked(ls, acs)
            for v in (2, 3, 4):
                pub.publish_weights(v, tensors(v))
            version, got = wait_for(src.poll_weights)
            # Announcements in quick succession collapse: the actor may skip versions, never go back.
            deadline = time.monotonic() + 30
            while version < 4 and time.monotonic() < deadline:
                nxt = src.poll_weights()
                if nxt is not None:
                    assert nxt[0] > version
                    version, got = nxt
                time.sleep(0.02)
            assert version == 4
            torch.testing.assert_close(got["w"], tensors(4)["w"])
            assert src.poll_weights() is None  # nothing new: not returned twice
            with pytest.raises(ValueError, match="strictly increase"):
                pub.publish_weights(4, tensors(9))
            # A stale announcement (from a confused second publisher) is ignored.
            _, stale = make_weights(2, tensors(2))
            acs_put(ls, RUN, stale)
            pub.publish_exploration(5, 0.25, "lae")
            rate = wait_for(src.poll_exploration)
            assert (rate.version, rate.value, rate.policy) == (5, 0.25, "lae")
            with pytest.raises(ValueError, match="strictly increase"):
                pub.publish_exploration(5, 0.5, "lae")
            pub.publish_exploration(6, 0.125, "lae")
            assert wait_for(src.poll_exploration).version == 6
            assert src.poll_exploration() is None
            time.sleep(0.3)
            assert src.poll_weights() is None
            assert src.stats()["ignored_stale"] >= 1


def acs_put(session: zenoh.Session, run_id: str, ann: WeightsAnnouncementMsg) -> None:
    session.put(RunKeys(run_id).weights_announce, wire.encode_weights_announcement(ann))


def test_late_actor_fetches_latest_when_learner_is_alive() -> None:
    with two_sessions() as (ls, acs), WeightsPublisher(ls, RUN) as pub:
        token = ls.liveliness().declare_token(RunKeys(RUN).learner_alive)
        try:
            pub.publish_weights(7, tensors(7))
            with ZenohWeightsSource(acs, RUN, fetch_timeout_s=5) as src:
                assert isinstance(src, WeightsSource)
                version, got = wait_for(src.poll_weights)
                assert version == 7
                torch.testing.assert_close(got["b"], tensors(7)["b"])
        finally:
            token.undeclare()


def test_a_restarted_learner_with_lower_versions_is_followed() -> None:
    """A learner that crashed before its first checkpoint restarts at version 0: actors must take it."""
    port = free_port()
    with open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as acs:
        with ZenohWeightsSource(acs, RUN, fetch_timeout_s=5) as src:
            for version in (9, 2):  # first incarnation at v9; the second starts over and is at v2
                with open_session(make_config(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as ls, \
                        WeightsPublisher(ls, RUN) as pub:
                    pub.publish_weights(version, tensors(version))
                    token = ls.liveliness().declare_token(RunKeys(RUN).learner_alive)
                    try:
                        got_version, got = wait_for(src.poll_weights, timeout_s=20)
                        assert got_version == version
                        torch.testing.assert_close(got["w"], tensors(version)["w"])
                    finally:
                        token.undeclare()
                if version == 9:  # the first learner is gone before the second appears
                    wait_for(lambda: True if src.stats().get("learner_gone") else None)
            assert src.stats()["learner_restarts"] == 1


def test_sha_and_size_mismatch_rejected(caplog: pytest.LogCaptureFixture) -> None:
    """A fetch answer that does not match the announcement is refused, counted and logged."""
    weights, ann = make_weights(3, tensors(3))
    wrong_sha = WeightsAnnouncementMsg(3, "0" * 64, ann.size_bytes, ann.created_ns)
    keys = RunKeys(RUN)
    with two_sessions() as (ls, acs):
        q = ls.declare_queryable(keys.weights_fetch, lambda query: query.reply(keys.weights_fetch,
                                                                               wire.encode_weights(weights)))
        try:
            with caplog.at_level(logging.WARNING), ZenohWeightsSource(acs, RUN, fetch_timeout_s=5) as src:
                wait_linked(ls, acs)
                acs_put(ls, RUN, wrong_sha)
                wait_for(lambda: src.stats().get("rejected_bad_weights"))
                assert src.poll_weights() is None
                wrong_size = WeightsAnnouncementMsg(4, ann.sha256_hex, ann.size_bytes + 1, ann.created_ns)
                acs_put(ls, RUN, wrong_size)  # v4 announced, v3 served: older than announced
                wait_for(lambda: src.stats()["rejected_bad_weights"] >= 2 or None)
                assert src.poll_weights() is None
                ls.put(keys.weights_announce, b"\x00garbage")
                wait_for(lambda: src.stats().get("rejected_bad_announcement"))
            assert "bad_weights" in caplog.text
        finally:
            q.undeclare()


def test_fetch_timeout_when_learner_is_gone(caplog: pytest.LogCaptureFixture) -> None:
    _, ann = make_weights(1, tensors(1))
    with two_sessions() as (ls, acs), caplog.at_level(logging.WARNING):
        with ZenohWeightsSource(acs, RUN, fetch_timeout_s=0.5) as src:
            wait_linked(ls, acs)
            acs_put(ls, RUN, ann)  # announced, but nobody serves the fetch
            wait_for(lambda: src.stats().get("rejected_fetch_failed"))
            assert src.poll_weights() is None
            assert src.poll_exploration() is None
    assert "fetch_failed" in caplog.text


def test_learner_weights_load_into_fresh_model() -> None:
    trained = RoManNet(SMALL, seed=1)
    with torch.no_grad():
        for p in trained.parameters():
            p.add_(0.01)
    fresh = RoManNet(SMALL, seed=2)
    with two_sessions() as (ls, acs), WeightsPublisher(ls, RUN) as pub:
        with ZenohWeightsSource(acs, RUN, fetch_timeout_s=5,
                                validate=lambda t: validate_tensors(fresh, t)) as src:
            wait_linked(ls, acs)
            pub.publish_weights(10, state_dict_to_tensors(trained))
            version, got = wait_for(src.poll_weights)
    assert version == 10
    load_tensors(fresh, got)
    for key, value in trained.state_dict().items():
        torch.testing.assert_close(fresh.state_dict()[key], value, rtol=0, atol=0)
