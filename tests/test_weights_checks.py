"""An actor checks every weights message before loading it (over real Zenoh sessions on loopback).

A rogue "learner" session announces and serves weights that are wrong in one way each: tampered in
transit, not safetensors, unknown / missing tensor names, a wrong shape, a wrong dtype, NaN, inf. The
actor's ZenohWeightsSource, validating against its RoManNet exactly as `romannet actor` does
(common/model.validate_tensors), must refuse each one with its reason in the log and hand out nothing,
so the actor keeps the weights it has; the next good version is then taken and loads bit for bit.
"""

from __future__ import annotations

import logging
import time

import pytest
import safetensors.torch
import torch

from romannet.common import romannet_pb2 as pb
from romannet.common import wire
from romannet.common.config import ModelConfig
from romannet.common.keys import RunKeys
from romannet.common.model import RoManNet, load_tensors, state_dict_to_tensors, validate_tensors
from romannet.common.weights_client import ZenohWeightsSource
from romannet.common.weightscodec import make_weights
from romannet.common.wire_messages import WeightsAnnouncementMsg, sha256_hex
from romannet.common.zenoh_session import free_port, make_config, open_session

RUN = "wchecks"
SMALL = ModelConfig(channels=4, residual_blocks=1)
KEY = "nets.pick.conv1.weight"


def _raw(tensors: dict[str, torch.Tensor]) -> bytes:
    """safetensors bytes without the learner's own checks (it refuses NaN; a rogue peer does not)."""
    return safetensors.torch.save({k: v.contiguous() for k, v in tensors.items()})


def _weights_message(version: int, payload: bytes, sha: str | None = None) -> bytes:
    """An encoded Weights message; sha (default: the payload's) is what the message claims."""
    msg = pb.Weights(version=version, sha256_hex=sha or sha256_hex(payload), safetensors=payload)
    msg.schema_version.major, msg.schema_version.minor = wire.SCHEMA_MAJOR, wire.SCHEMA_MINOR
    return msg.SerializeToString()


def _bad_cases(good: dict[str, torch.Tensor]) -> dict[str, tuple[bytes, str | None, str]]:
    """name -> (safetensors payload, the SHA-256 the message claims (None: the payload's), a phrase the
    rejection's log line must hold)."""
    def changed(key: str, value: torch.Tensor | None) -> bytes:
        out = dict(good)
        if value is None:
            del out[key]
        else:
            out[key] = value
        return _raw(out)

    ok_payload = _raw(good)
    tampered = bytearray(ok_payload)
    tampered[-1] ^= 0xFF  # one bit flipped in transit; the message still claims the original's digest
    return {
        "tampered": (bytes(tampered), sha256_hex(ok_payload), "SHA-256"),
        "not_safetensors": (b"\x00" * 64, None, "invalid safetensors"),
        "unknown_name": (changed("nets.throw.conv1.weight", torch.zeros(3)), None, "unexpected keys"),
        "missing_name": (changed(KEY, None), None, "missing keys"),
        "shape": (changed(KEY, torch.zeros(2, 2)), None, "has shape"),
        "dtype": (changed(KEY, good[KEY].double()), None, "has dtype"),
        "nan": (changed(KEY, good[KEY].clone().fill_(float("nan"))), None, "NaN"),
        "inf": (changed(KEY, good[KEY].clone().fill_(float("inf"))), None, "NaN or inf"),
    }


def _wait(fn, timeout_s: float = 15.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = fn()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"nothing within {timeout_s} s")


def test_actor_refuses_bad_weights_with_a_reason_and_keeps_its_own(caplog: pytest.LogCaptureFixture) -> None:
    keys = RunKeys(RUN)
    actor_model = RoManNet(SMALL, seed=0)
    before = state_dict_to_tensors(actor_model)
    trained = {k: v + 0.5 if v.is_floating_point() else v for k, v in before.items()}
    cases = _bad_cases(trained)
    served = {i + 1: _weights_message(i + 1, payload, sha) for i, (payload, sha, _) in enumerate(cases.values())}
    port = free_port()
    with open_session(make_config(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as rogue, \
            open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as actor:

        def serve(query) -> None:
            query.reply(keys.weights_fetch, served[int(query.parameters.get("version"))])

        queryable = rogue.declare_queryable(keys.weights_fetch, serve)
        try:
            with caplog.at_level(logging.WARNING), ZenohWeightsSource(
                    actor, RUN, fetch_timeout_s=5, validate=lambda t: validate_tensors(actor_model, t)) as src:
                _wait(lambda: any(r.ok is not None for r in actor.get(keys.weights_fetch + "?version=1",
                                                                      timeout=1.0)))
                for version, data in list(served.items()):
                    body = pb.Weights.FromString(data)  # announced as served: only the content is wrong
                    ann = WeightsAnnouncementMsg(version, body.sha256_hex, len(body.safetensors), time.time_ns())
                    rogue.put(keys.weights_announce, wire.encode_weights_announcement(ann))
                    _wait(lambda v=version: src.stats().get("rejected_bad_weights", 0) >= v)
                    assert src.poll_weights() is None, f"case {version} was handed to the actor"
                assert src.stats()["rejected_bad_weights"] == len(cases)
                assert state_dict_to_tensors(actor_model).keys() == before.keys()
                assert all(torch.equal(state_dict_to_tensors(actor_model)[k], before[k]) for k in before)

                good, good_ann = make_weights(len(cases) + 1, trained)
                served[good.version] = wire.encode_weights(good)
                rogue.put(keys.weights_announce, wire.encode_weights_announcement(good_ann))
                version, tensors = _wait(src.poll_weights)
        finally:
            queryable.undeclare()
    assert version == len(cases) + 1
    load_tensors(actor_model, tensors)
    assert all(torch.equal(actor_model.state_dict()[k], trained[k]) for k in trained)
    for i, (name, (_, _, phrase)) in enumerate(cases.items()):
        lines = [r.getMessage() for r in caplog.records if f"weights {i + 1} refused" in r.getMessage()]
        assert len(lines) == 1 and phrase in lines[0], (name, phrase, lines)
        assert "keeping v-1" in lines[0]  # nothing was ever taken: the actor's initial weights stay
