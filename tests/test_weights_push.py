"""Weights put once per version through a Zenoh router, the query path for late joiners, and bad pushes.

Real sessions on loopback, multicast scouting off: a router session listens on a free port; the learner and
the actors are clients of it, so everything goes through the router as on a fleet network.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import Any

import pytest
import torch
import zenoh

from romannet.common import romannet_pb2 as pb
from romannet.common import wire
from romannet.common.config import ModelConfig
from romannet.common.keys import RunKeys
from romannet.common.model import RoManNet, state_dict_to_tensors, validate_tensors
from romannet.common.weights_client import ZenohWeightsSource
from romannet.common.weightscodec import make_weights
from romannet.common.wire_messages import sha256_hex
from romannet.common.zenoh_session import free_port, make_config, open_session
from romannet.deploy.router import make_router_config
from romannet.learner.publisher import WeightsPublisher

RUN = "wpush"
KEYS = RunKeys(RUN)
SMALL = ModelConfig(channels=4, residual_blocks=1)


def _client(endpoint: str) -> zenoh.Config:
    config = make_config(listen=[], connect=[endpoint])
    config.insert_json5("mode", '"client"')
    return config


@contextmanager
def fleet(actors: int) -> Iterator[tuple[zenoh.Session, list[zenoh.Session]]]:
    """A router, the learner's session and `actors` actor sessions, all clients of the router."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session(make_router_config(None, listen=[endpoint])), ExitStack() as stack:
        learner = stack.enter_context(open_session(_client(endpoint)))
        yield learner, [stack.enter_context(open_session(_client(endpoint))) for _ in range(actors)]


def wait_for(fn: Callable[[], Any], timeout_s: float = 15.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = fn()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"nothing within {timeout_s} s")


def wait_subscribed(learner: zenoh.Session, timeout_s: float = 10.0) -> None:
    """Until the router has told the learner of a subscriber on the data key (one is enough here)."""
    publisher = learner.declare_publisher(KEYS.weights_data)
    try:
        wait_for(lambda: publisher.matching_status.matching, timeout_s)
    finally:
        publisher.undeclare()


def tensors(seed: int) -> dict[str, torch.Tensor]:
    torch.manual_seed(seed)
    return {k: (torch.rand_like(v) + 0.5 if k.endswith("running_var") else torch.randn_like(v))
            if v.is_floating_point() else v for k, v in state_dict_to_tensors(RoManNet(SMALL)).items()}


def test_one_put_per_version_reaches_every_actor_and_a_late_one_fetches() -> None:
    model = RoManNet(SMALL)
    with fleet(3) as (ls, actor_sessions), WeightsPublisher(ls, RUN, wire_dtype="bf16") as pub, ExitStack() as stack:
        sources = [stack.enter_context(ZenohWeightsSource(s, RUN, fetch_timeout_s=5,
                                                          validate=lambda t: validate_tensors(model, t)))
                   for s in actor_sessions[:2]]
        wait_subscribed(ls)
        time.sleep(0.3)  # the second actor's subscriber too (no per-subscriber matching in zenoh)
        for version in (1, 2):
            pub.publish_weights(version, tensors(version))
            for src in sources:
                got, received = wait_for(src.poll_weights)
                assert got == version
                expected = tensors(version)["nets.push.q_head.weight"]
                assert torch.equal(received["nets.push.q_head.weight"], expected)  # fp32 on the wire
                conv = received["nets.push.conv2.weight"]
                assert torch.equal(conv, tensors(version)["nets.push.conv2.weight"].bfloat16().float())
        assert pub.pushed == 2
        # Each version went out once, as a put: no actor needed a query.
        assert pub.served == 0, [s.stats() for s in sources]
        assert all(src.stats().get("taken_pushed") == 2 and not src.stats().get("fetched") for src in sources)
        # An actor that joins now missed both puts: the learner's token makes it fetch the newest.
        token = ls.liveliness().declare_token(KEYS.learner_alive)
        try:
            late = stack.enter_context(ZenohWeightsSource(actor_sessions[2], RUN, fetch_timeout_s=5))
            assert wait_for(late.poll_weights)[0] == 2
            assert late.stats()["fetched"] == 1
            # ... and takes the next version from the put like the others.
            pub.publish_weights(3, tensors(3))
            assert all(wait_for(src.poll_weights)[0] == 3 for src in [*sources, late])
            assert late.stats()["taken_pushed"] == 1
        finally:
            token.undeclare()


def _message(version: int, payload: bytes, sha: str | None = None) -> bytes:
    msg = pb.Weights(version=version, sha256_hex=sha or sha256_hex(payload), safetensors=payload)
    msg.schema_version.major, msg.schema_version.minor = wire.SCHEMA_MAJOR, wire.SCHEMA_MINOR
    return msg.SerializeToString()


def test_bad_pushes_are_refused_in_one_line_each_and_the_weights_stay(caplog: pytest.LogCaptureFixture) -> None:
    model = RoManNet(SMALL)
    good3, _ = make_weights(3, tensors(3))
    good4, _ = make_weights(4, tensors(4))
    wrong_shape = {**tensors(5), "nets.pick.conv2.weight": torch.zeros(3, 3)}
    encoded3 = wire.encode_weights(good3)
    cases = {  # name -> (message bytes, a phrase its log line holds)
        "truncated": (encoded3[: len(encoded3) // 2], "refused"),
        "wrong_element_count": (wire.encode_weights(make_weights(5, wrong_shape)[0]), "has shape"),
        "wrong_hash": (_message(6, good4.safetensors, sha256_hex(good3.safetensors)), "SHA-256"),
        "older": (wire.encode_weights(make_weights(2, tensors(2))[0]), "not newer"),
        "same_version_other_weights": (wire.encode_weights(make_weights(3, tensors(9))[0]), "not newer"),
    }
    with fleet(1) as (ls, (acs,)), caplog.at_level(logging.WARNING), \
            ZenohWeightsSource(acs, RUN, fetch_timeout_s=5, validate=lambda t: validate_tensors(model, t)) as src:
        wait_subscribed(ls)
        ls.put(KEYS.weights_data, encoded3, congestion_control=zenoh.CongestionControl.BLOCK)
        assert wait_for(src.poll_weights)[0] == 3
        for name, (data, phrase) in cases.items():
            before = len(caplog.records)
            ls.put(KEYS.weights_data, data, congestion_control=zenoh.CongestionControl.BLOCK)
            wait_for(lambda b=before: len(caplog.records) > b)
            time.sleep(0.1)  # a second line would come now
            lines = [r.getMessage() for r in caplog.records[before:]]
            assert len(lines) == 1 and phrase in lines[0] and "keeping v3" in lines[0], (name, lines)
            assert src.poll_weights() is None, name
        assert not any(r.exc_info for r in caplog.records)  # no tracebacks
        # The actor still takes the next good version.
        ls.put(KEYS.weights_data, wire.encode_weights(good4), congestion_control=zenoh.CongestionControl.BLOCK)
        assert wait_for(src.poll_weights)[0] == 4


def test_an_announcement_that_overtakes_its_pushed_data_waits_for_it_and_an_unpushed_one_is_fetched() -> None:
    """Zenoh delivers each key on its own thread, so the announcement of even the first version can come
    before its data: an announcement that says `pushed` waits for the put; one that does not is fetched."""
    queries: list[str] = []
    v2, ann2 = make_weights(2, tensors(2))

    def serve(query: zenoh.Query) -> None:
        queries.append(str(query.parameters))
        query.reply(KEYS.weights_fetch, wire.encode_weights(v2))

    with fleet(1) as (ls, (acs,)), ZenohWeightsSource(acs, RUN, fetch_timeout_s=5) as src:
        queryable = ls.declare_queryable(KEYS.weights_fetch, serve)
        try:
            wait_subscribed(ls)
            v1, ann1 = make_weights(1, tensors(1))
            ls.put(KEYS.weights_announce, wire.encode_weights_announcement(dataclasses.replace(ann1, pushed=True)))
            time.sleep(0.3)  # the data trails its announcement
            ls.put(KEYS.weights_data, wire.encode_weights(v1), congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_for(src.poll_weights)[0] == 1
            assert queries == [] and src.stats()["taken_pushed"] == 1
            ls.put(KEYS.weights_announce, wire.encode_weights_announcement(ann2))  # pushed=False: fetch at once
            assert wait_for(src.poll_weights)[0] == 2
            assert queries == ["version=2"] and src.stats()["fetched"] == 1
        finally:
            queryable.undeclare()
