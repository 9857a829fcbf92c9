"""State dicts <-> safetensors bytes, for weights on the wire and on disk (never pickle, never torch.load).

Kept apart from common/wire.py so that processes which only move bytes (the replay server) do not
import torch.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import safetensors.torch
import torch

from .errors import DecodeError
from .tensor_checks import all_finite
from .wire_messages import MAX_WEIGHTS_BYTES, WeightsAnnouncementMsg, WeightsMsg, sha256_hex
from .wire_validate import show


def _non_finite(tensors: Mapping[str, torch.Tensor]) -> list[str]:
    return [name for name, t in tensors.items() if not all_finite(t)]


def encode_state_dict(tensors: Mapping[str, torch.Tensor]) -> bytes:
    """safetensors bytes of a state dict (copied to contiguous CPU tensors).

    Raises ValueError on non-finite values: a diverged learner must not ship NaN weights to the fleet.
    """
    cpu = {str(name): t.detach().to("cpu").contiguous() for name, t in tensors.items()}
    bad = _non_finite(cpu)
    if bad:
        raise ValueError(f"tensors {show(bad)} contain NaN or inf; refusing to encode them")
    return safetensors.torch.save(cpu, metadata={"format": "pt"})


def decode_state_dict(data: bytes, expected_sha256: str | None = None) -> dict[str, torch.Tensor]:
    """State dict of safetensors bytes, checked against expected_sha256 (hex) when given.

    Raises DecodeError if the bytes are too large, do not match the digest, are not safetensors, or hold
    non-finite floating-point values.
    """
    try:
        if not isinstance(data, bytes):
            raise ValueError(f"expected bytes, got {type(data).__name__}")
        if not 1 <= len(data) <= MAX_WEIGHTS_BYTES:
            raise ValueError(f"payload is {len(data)} bytes; must be 1..{MAX_WEIGHTS_BYTES}")
        if expected_sha256 is not None and sha256_hex(data) != expected_sha256:
            raise ValueError(f"SHA-256 {sha256_hex(data)} differs from the expected {show(expected_sha256)}")
        tensors = safetensors.torch.load(data)
        bad = _non_finite(tensors)
        if bad:
            raise ValueError(f"tensors {show(bad)} contain NaN or inf")
        return tensors
    except Exception as exc:  # the contract: DecodeError and nothing else (safetensors raises its own types)
        detail = str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"
        raise DecodeError(f"invalid safetensors weights: {detail}") from exc


def make_weights(version: int, tensors: Mapping[str, torch.Tensor],
                 created_ns: int | None = None) -> tuple[WeightsMsg, WeightsAnnouncementMsg]:
    """A weights message and its announcement for one version of a state dict.

    created_ns: ns since the Unix epoch; now if None.
    """
    payload = encode_state_dict(tensors)
    digest = sha256_hex(payload)
    created = time.time_ns() if created_ns is None else created_ns
    return (WeightsMsg(version, digest, payload),
            WeightsAnnouncementMsg(version, digest, len(payload), created))


def weights_state_dict(msg: WeightsMsg) -> dict[str, torch.Tensor]:
    """State dict of a (decoded) weights message; raises DecodeError as decode_state_dict does."""
    # No second hash: WeightsMsg checked its (immutable) payload against sha256_hex when it was built.
    return decode_state_dict(msg.safetensors)
