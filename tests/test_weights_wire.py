"""Weights in bf16 on the wire: half the bytes, and a bf16 actor computes the same bits from them.

The learner rounds the body's convolution weights to bf16 (common/weights_wire.py); a bf16
InferenceEngine rounds them so itself before folding BatchNorm, so its outputs from the received weights
must equal, bit for bit, its outputs from the learner's fp32 weights.
"""

from __future__ import annotations

import pytest
import safetensors.torch
import torch

from romannet.common.config import ModelConfig, load_config
from romannet.common.errors import ConfigError
from romannet.common.model import RoManNet, state_dict_to_tensors
from romannet.common.policy import InferenceEngine
from romannet.common.weights_wire import bf16_on_wire, from_wire, resolve_wire_dtype, to_wire
from romannet.common.weightscodec import decode_state_dict, encode_state_dict

SMALL = ModelConfig(channels=8, residual_blocks=1, precision="bf16", num_threads=1)


def _trained(seed: int) -> dict[str, torch.Tensor]:
    """A state dict with non-trivial BatchNorm statistics, as a trained net has."""
    torch.manual_seed(seed)
    tensors = state_dict_to_tensors(RoManNet(SMALL, seed=seed))
    for name, t in tensors.items():
        if name.endswith("running_var"):
            t.uniform_(0.5, 2.0)
        elif name.endswith(("running_mean", "bias")):
            t.normal_(0.0, 0.1)
    return tensors


def test_bf16_goes_to_the_body_convolutions_only() -> None:
    tensors = _trained(0)
    on_wire = {name for name, t in tensors.items() if bf16_on_wire(name, t)}
    assert "nets.push.conv2.weight" in on_wire and "nets.pick.res.0.conv1.weight" in on_wire
    assert "nets.place.conv6.weight" in on_wire and "nets.push.deconv1.weight" in on_wire
    # What a bf16 engine uses at more than bf16 precision stays fp32.
    for kept in ("nets.push.conv1.weight", "nets.push.q_head.weight", "nets.push.rot_head.weight",
                 "nets.push.conv2.bias", "nets.push.bn2.running_var", "nets.push.bn1.num_batches_tracked"):
        assert kept in tensors and kept not in on_wire, kept
    fp32_bytes = len(encode_state_dict(to_wire(tensors, "fp32")))
    bf16_bytes = len(encode_state_dict(to_wire(tensors, "bf16")))
    assert bf16_bytes < 0.6 * fp32_bytes


def test_a_bf16_engine_computes_the_same_bits_from_the_wire_weights() -> None:
    tensors = _trained(1)
    received = from_wire(decode_state_dict(encode_state_dict(to_wire(tensors, "bf16"))))
    assert all(received[k].dtype == tensors[k].dtype for k in tensors)
    direct = InferenceEngine(RoManNet(SMALL, seed=5), SMALL, parallel_nets=False)
    direct.load_state(tensors)
    wired = InferenceEngine(RoManNet(SMALL, seed=6), SMALL, parallel_nets=False)
    wired.load_state(received)
    x = torch.rand(1, 4, 32, 32)
    a, b = direct.forward(x, ("push", "pick", "place")), wired.forward(x, ("push", "pick", "place"))
    assert all(torch.equal(a[p], b[p]) for p in a)


def test_fp32_on_the_wire_is_unchanged_and_only_bf16_is_widened() -> None:
    tensors = _trained(2)
    assert all(torch.equal(v, tensors[k]) for k, v in from_wire(to_wire(tensors, "fp32")).items())
    # A float64 or fp16 tensor is not widened: the model's dtype check refuses it as before.
    odd = from_wire({"a": torch.zeros(2, dtype=torch.float64), "b": torch.zeros(2, dtype=torch.float16)})
    assert odd["a"].dtype == torch.float64 and odd["b"].dtype == torch.float16
    raw = safetensors.torch.save({"w": torch.ones(2, dtype=torch.bfloat16)})
    assert from_wire(decode_state_dict(raw))["w"].dtype == torch.float32


def test_wire_dtype_setting() -> None:
    assert resolve_wire_dtype("fp32", "bf16") == "fp32"
    assert resolve_wire_dtype("bf16", "fp32") == "bf16"
    assert resolve_wire_dtype("auto", "fp32") == "fp32"
    assert resolve_wire_dtype("auto", "bf16") == "bf16"
    with pytest.raises(ValueError, match="wire dtype"):
        to_wire({}, "fp16")
    with pytest.raises(ConfigError, match="weights_wire_dtype"):
        load_config(None, ["learner.weights_wire_dtype=fp16"])
