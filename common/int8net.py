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

Without VNNI (AVX2, AVX-512 without VNNI) oneDNN multiplies uint8 by int8 with vpmaddubsw, which adds two
products in int16 and saturates: 255 x 127 x 2 overflows. A trained net's activations and weights reach those
extremes together often enough that the saturated sums moved its Q maps by up to 1.3x their std (measured,
docs/benchmarks.md). There the weights take 7 bits (-63..63: 255 x 63 x 2 fits in int16), as the x86
quantisation guides advise (PyTorch's reduce_range does the same on the activations; the weights' bit costs
less: activation error dominates, measured).

int8 is not exact: a decision whose best two pixels it cannot order is rerun with `exact`, the fp32 FastNet
(common/policy.py, `InferenceEngine.near_ties`). How close is "cannot order" is measured per net when it is
built (`error_spread`): the spread of its int8 Q error on one small seeded scene, which predicted the error at
224 px within a few % on trained and random-init nets alike, where a share of the Q map's std did not (a
trained net's int8 error is 15-40x a random one's relative to its maps, docs/benchmarks.md).
"""

from __future__ import annotations

import math
import platform
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .fastnet import FastNet, _Layer
from .model import GRConvNet, preprocess
from .scenes import synthetic_scene

_MIN_SCALE = 1e-12  # an all-zero tensor still gets a valid scale
_NO_DILATION = [1, 1]
VNNI_CPU_FLAGS = ("avx512_vnni", "avx_vnni", "amx_int8")
# oneDNN ISA limits (ONEDNN_MAX_CPU_ISA) below its first VNNI level: int8 dot products through vpmaddubsw.
ONEDNN_ISAS_WITHOUT_VNNI = ("SSE41", "AVX", "AVX2", "AVX512_CORE")
WEIGHT_BITS_VNNI = 8
WEIGHT_BITS_NO_VNNI = 7
# The scene int8's error is measured on: 64 px costs ~1/12 of a 224 px pass and gave the same error spread.
CALIBRATION_SIZE_PX = 64
CALIBRATION_SEED = 7


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


def int8_weight_bits(cpu_flags: frozenset[str], isa_cap: str) -> int:
    """The bits int8 weights may use without saturating oneDNN's int16 pair sums: 8 with VNNI, else 7.
    isa_cap: ONEDNN_MAX_CPU_ISA as set ("" for none)."""
    vnni = any(flag in cpu_flags for flag in VNNI_CPU_FLAGS) and isa_cap.upper() not in ONEDNN_ISAS_WITHOUT_VNNI
    return WEIGHT_BITS_VNNI if vnni else WEIGHT_BITS_NO_VNNI


def quantize_weight(weight: Tensor, bits: int = WEIGHT_BITS_VNNI) -> tuple[Tensor, Tensor]:
    """Symmetric int8 per output channel (dim 0) in `bits` bits (8: -127..127, 7: -63..63): (int8 weights, fp32
    scales). oneDNN takes zero points of 0."""
    top = float(2 ** (bits - 1) - 1)
    w = weight.detach().float().contiguous()
    scales = (w.abs().amax(dim=(1, 2, 3)) / top).clamp_min(_MIN_SCALE)
    return torch.round(w / scales.view(-1, 1, 1, 1)).clamp_(-top, top).to(torch.int8), scales


class _QConv:
    """One convolution in int8 by oneDNN: uint8 input, int8 weights per output channel, fp32 bias and output."""

    def __init__(self, weight: Tensor, bias: Tensor, stride: int, padding: int,
                 weight_bits: int = WEIGHT_BITS_VNNI):
        self.weight, self.w_scales = quantize_weight(weight, weight_bits)
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
    """Inference form of one GRConvNet with an int8 trunk: (B,4,H,W) fp32 → (B,H,W,K+R) fp32, as FastNet."""

    def __init__(self, net: GRConvNet, fused: bool | None = None, weight_bits: int = WEIGHT_BITS_VNNI):
        """weight_bits: 8 where oneDNN has VNNI, else 7 (`int8_weight_bits`)."""
        # The fp32 net: its first conv, transposed convs and tail are ours too, and it reruns near ties.
        self.exact = f = FastNet(net, "fp32", fused)
        self.weight_bits = weight_bits
        with torch.no_grad():
            self.conv2 = _QConv(f.layers[1].weight, f.layers[1].bias, 2, 1, weight_bits)
            self.conv3 = _QConv(f.layers[2].weight, f.layers[2].bias, 2, 1, weight_bits)
            self.res = [(_QConv(first.weight, first.bias, 1, 1, weight_bits),
                         _QConv(second.weight, second.bias, 1, 1, weight_bits)) for first, second in f.res]
            # Fold the heads into conv6 only where that makes it narrower (fewer outputs than channels).
            self.head = _Layer(*folded_head(f), torch.float32, 1, 4, False, f.conv6.fused) \
                if f.outputs < f.conv6.weight.shape[0] else None
            self.error_spread = error_spread(self, calibration_input())

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


def calibration_input(size_px: int = CALIBRATION_SIZE_PX) -> Tensor:
    """The fixed (1,4,size,size) scene int8's error is measured on."""
    return preprocess(*synthetic_scene(np.random.default_rng(CALIBRATION_SEED), size_px, size_px))


def error_spread(net: Int8Net, x: Tensor) -> float:
    """max - min over pixels of int8's Q error against fp32 on x: no two pixels' errors differ by more, so two
    pixels whose int8 Q values are further apart keep their order (on x, and about as much on other scenes:
    measured). inf where the maps are not finite (weights a diverged learner sent)."""
    with torch.inference_mode():
        k = net.exact.q_channels
        error = net(x)[0, ..., :k] - net.exact(x)[0, ..., :k]
        spread = float(error.max() - error.min())
    return spread if math.isfinite(spread) else math.inf
