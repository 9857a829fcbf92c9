"""Which weights may travel in bf16: the ones a bf16 actor rounds to bf16 before it uses them.

    wire = to_wire(tensors, "bf16")      # learner: the body's convolution weights as bf16, the rest fp32
    tensors = from_wire(decoded)         # actor: bf16 -> fp32 (exact), then the usual validation

A bf16 InferenceEngine (common/policy.py) rounds every convolution weight of a net's body to bf16 before it
folds BatchNorm into it, so such an actor computes bit for bit the same from these weights as from the
learner's fp32 ones. What it uses at more than bf16 precision stays fp32 on the wire: the first layer (split
into two bf16 halves there), the 1x1 Q and rotation heads, every bias and BatchNorm tensor. An fp32 actor
given bf16 weights acts on the rounded values: the learner sends fp32 to such a fleet
(learner.weights_wire_dtype).
"""

from __future__ import annotations

import re
from collections.abc import Mapping

import torch

from .policy import resolve_inference_precision

WIRE_DTYPES = ("fp32", "bf16")
# A net's first convolution: the bf16 engine keeps it at ~16 mantissa bits (hi + lo halves).
_FIRST_LAYER = re.compile(r"(^|\.)nets\.[^.]+\.conv1\.weight$")
_HEAD = re.compile(r"_head\.weight$")


def bf16_on_wire(name: str, tensor: torch.Tensor) -> bool:
    """Whether a bf16 actor uses `name` only rounded to bf16: a body convolution's 4-D fp32 weight."""
    return (tensor.dtype == torch.float32 and tensor.dim() == 4 and name.endswith(".weight")
            and not _FIRST_LAYER.search(name) and not _HEAD.search(name))


def to_wire(tensors: Mapping[str, torch.Tensor], dtype: str) -> dict[str, torch.Tensor]:
    """The tensors as they travel for wire dtype "fp32" (unchanged) or "bf16" (see bf16_on_wire)."""
    if dtype not in WIRE_DTYPES:
        raise ValueError(f"weights wire dtype {dtype!r} must be one of {WIRE_DTYPES}")
    if dtype == "fp32":
        return dict(tensors)
    return {k: v.to(torch.bfloat16) if bf16_on_wire(k, v) else v for k, v in tensors.items()}


def from_wire(tensors: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """bf16 tensors widened to fp32 (exact); every other dtype as it came, for the model's own checks."""
    return {k: v.float() if v.dtype == torch.bfloat16 else v for k, v in tensors.items()}


def resolve_wire_dtype(wire_dtype: str, model_precision: str) -> str:
    """learner.weights_wire_dtype as "fp32" or "bf16": "auto" is bf16 where model.precision resolves to bf16
    on this machine (the learner's; on one machine, the actors' too). int8 actors quantise fp32 weights (precision
    "int8": fp32)."""
    if wire_dtype != "auto":
        to_wire({}, wire_dtype)  # raises ValueError on an unknown dtype
        return wire_dtype
    if model_precision == "int8":  # resolved on the actors, which may have oneDNN's int8 ops where we do not
        return "fp32"
    return "bf16" if resolve_inference_precision(model_precision) == "bf16" else "fp32"
