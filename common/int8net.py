"""Int8Net: one GRConvNet with its trunk in int8, for decisions on CPUs without native bf16 (precision "int8").

What runs in int8, what stays fp32, and why (measured in docs/benchmarks.md, "int8 decisions"):

* conv2, conv3 and the residual blocks (most of the multiply-adds once the heads are folded) run as oneDNN
  int8 convolutions on plain uint8 tensors (`torch.ops.onednn.qconv2d_pointwise`, the op PyTorch's x86
  quantisation lowers to): weights int8 per output channel; each input quantised per tensor at its own range
  (dynamic scales: nothing to calibrate, so new weights cost only their quantisation, and no input is clipped
  to another's range). The residual stream stays fp32: each block's second conv adds into it (oneDNN's sum
  post-op), so it is not rounded again at every block.
* fp32: the first conv (the raw image's 4 channels), the transposed convs (PyTorch has no oneDNN int8 op for
  them; FBGEMM's was slower than fp32 here, and the x86 engine's oneDNN one gave wrong outputs for unequal
  in/out channels in torch 2.13) and the output conv, into which the 1x1 heads are folded (both linear, so
  exact): 3 output channels instead of 32 make the largest layer ~4x cheaper.

int8 is not exact: a decision whose best two pixels it cannot order is rerun with `exact`, the fp32 FastNet
(common/policy.py, `InferenceEngine.near_ties`).
"""

from __future__ import annotations

import math
import platform
from dataclasses import dataclass

import torch
from torch import Tensor

from .fastnet import FastNet, _Layer
from .model import GRConvNet

_MIN_SCALE = 1e-12  # an all-zero tensor still gets a valid scale
_NO_DILATION = [1, 1]


def int8_ops_available() -> bool:
    """Whether this PyTorch build runs oneDNN's int8 convolutions on this machine (x86 builds with oneDNN)."""
    if not torch.backends.mkldnn.is_available() or platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    try:
        return all(hasattr(torch.ops.onednn, name) for name in ("qconv2d_pointwise", "qconv_prepack"))
    except (AttributeError, RuntimeError):
        return False


@dataclass(frozen=True)
class QParams:
    """uint8 quantisation of a tensor: real = (q - zero_point) * scale."""

    scale: float
    zero_point: int


def act_qparams(lo: float, hi: float) -> QParams:
    """The uint8 scale and zero point that cover [lo, hi] and hold 0 exactly (ReLU outputs, zero padding)."""
    lo, hi = min(lo, 0.0), max(hi, 0.0)
    scale = max((hi - lo) / 255.0, _MIN_SCALE)
    return QParams(scale, int(round(-lo / scale)))


def quantize_u8(x: Tensor, q: QParams) -> Tensor:
    """fp32 → uint8 at q (round half up, saturating) in three passes, keeping x's memory format."""
    offset = torch.tensor(q.zero_point + 0.5)  # + 0.5, then truncation: rounds the clamped values
    return torch.add(offset, x, alpha=1.0 / q.scale).clamp_(0.0, 255.0).to(torch.uint8)


def quantize_weight(weight: Tensor) -> tuple[Tensor, Tensor]:
    """Symmetric int8 per output channel (dim 0): (int8 weights, fp32 scales). oneDNN takes zero points of 0."""
    w = weight.detach().float().contiguous()
    scales = (w.abs().amax(dim=(1, 2, 3)) / 127.0).clamp_min(_MIN_SCALE)
    return torch.round(w / scales.view(-1, 1, 1, 1)).clamp_(-127, 127).to(torch.int8), scales


class _QConv:
    """One convolution in int8 by oneDNN: uint8 input, int8 weights per output channel, fp32 bias and output."""

    def __init__(self, weight: Tensor, bias: Tensor, stride: int, padding: int):
        self.weight, self.w_scales = quantize_weight(weight)
        self.w_zero_points = torch.zeros(self.weight.shape[0], dtype=torch.int32)
        self.bias = bias.detach().float().contiguous()
        self.stride, self.padding = [stride] * 2, [padding] * 2
        self.packed: Tensor | None = None
        self.packed_for: tuple[int, ...] | None = None

    def _packed_weight(self, x: Tensor) -> Tensor:
        # oneDNN picks the weight layout for an input shape; repack if the shape changes (rare). The input's
        # scale and zero point given here do not matter: each call passes its own.
        if self.packed_for != tuple(x.shape):
            self.packed = torch.ops.onednn.qconv_prepack(self.weight, self.w_scales, 1.0, 0, self.stride,
                                                         self.padding, _NO_DILATION, 1, list(x.shape))
            self.packed_for = tuple(x.shape)
        return self.packed

    def __call__(self, x: Tensor, x_q: QParams, relu: bool = False, add_to: Tensor | None = None) -> Tensor:
        """conv(x) [+ add_to, in place] [then ReLU] in fp32, for x uint8 at x_q."""
        op, w, unary = torch.ops.onednn.qconv2d_pointwise, self._packed_weight(x), "relu" if relu else "none"
        if add_to is not None:
            return op.binary(x, x_q.scale, x_q.zero_point, w, self.w_scales, self.w_zero_points, add_to,
                             self.bias, self.stride, self.padding, _NO_DILATION, 1, 1.0, 0, torch.float32, 1.0, 0,
                             "sum", 1.0, unary, [], "")
        return op(x, x_q.scale, x_q.zero_point, w, self.w_scales, self.w_zero_points, self.bias, self.stride,
                  self.padding, _NO_DILATION, 1, 1.0, 0, torch.float32, unary, [], "")


class _NonFinite(ValueError):
    """An activation held NaN or infinity: the weights are unusable, and the fp32 net says so in its Q maps."""


def quantize_dynamic(x: Tensor, signed: bool = True) -> tuple[Tensor, QParams]:
    """x as uint8 at the scale and zero point of its own range; signed False: x >= 0 (a ReLU's output).
    (amax and amin, not aminmax: ~10x faster on channels_last tensors.)"""
    hi = float(x.amax())
    lo = float(x.amin()) if signed else 0.0
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise _NonFinite
    q = act_qparams(lo, hi)
    return quantize_u8(x, q), q


def folded_head(fast: FastNet) -> tuple[Tensor, Tensor]:
    """conv6 followed by the 1x1 heads as one conv (weights (outputs, C, 9, 9), bias (outputs,)), in float64
    then rounded once."""
    w6, b6 = fast.conv6.weight.double(), fast.conv6.bias.double()
    heads = fast.heads_w.double().t()  # (outputs, C)
    weight = torch.einsum("oc,cikl->oikl", heads, w6)
    return weight.float(), (heads @ b6 + fast.heads_b.double()).float()


class Int8Net:
    """Inference form of one GRConvNet with an int8 trunk: (B,4,H,W) fp32 → (B,H,W,1+R) fp32, as FastNet."""

    def __init__(self, net: GRConvNet, fused: bool | None = None):
        # The fp32 net: its first conv, transposed convs and tail are ours too, and it reruns near ties.
        self.exact = f = FastNet(net, "fp32", fused)
        with torch.no_grad():
            self.conv2 = _QConv(f.layers[1].weight, f.layers[1].bias, 2, 1)
            self.conv3 = _QConv(f.layers[2].weight, f.layers[2].bias, 2, 1)
            self.res = [(_QConv(first.weight, first.bias, 1, 1), _QConv(second.weight, second.bias, 1, 1))
                        for first, second in f.res]
            # Fold the heads into conv6 only where that makes it narrower (fewer outputs than channels).
            self.head = _Layer(*folded_head(f), torch.float32, 1, 4, False, f.conv6.fused) \
                if f.outputs < f.conv6.weight.shape[0] else None

    def __call__(self, x: Tensor) -> Tensor:
        try:
            features = self.trunk(x)
        except _NonFinite:
            return self.exact(x)
        if self.head is None:
            return self.exact.tail(features)
        out = self.head(features, relu=False).permute(0, 2, 3, 1).contiguous()
        return out

    def trunk(self, x: Tensor) -> Tensor:
        """(B,4,H,W) fp32 input → the (B,C,H,W) features conv6 reads; each int8 conv's input is quantised at
        its own range, so no scale is calibrated and new weights cost only their quantisation."""
        f = self.exact
        x = f.layers[0](x.contiguous(memory_format=torch.channels_last))
        x = self.conv2(*quantize_dynamic(x, signed=False), relu=True)
        x = self.conv3(*quantize_dynamic(x, signed=False), relu=True)  # the residual stream, fp32
        for first, second in self.res:
            y = first(*quantize_dynamic(x), relu=True)
            x = second(*quantize_dynamic(y, signed=False), add_to=x)
        for layer in f.up:
            x = layer(x)
        return x
