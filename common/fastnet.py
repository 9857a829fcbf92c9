"""FastNet: the inference-only form of one GRConvNet that the InferenceEngine (common/policy.py) runs.

* BatchNorm folded into the preceding (transposed) convolution, so a conv + bias + ReLU is one call;
* channels_last activations and, where the PyTorch build has oneDNN's fused ops, weights prepacked once
  (`mkldnn._reorder_convolution_weight`) and convolutions fused with ReLU / the residual add — the same
  kernels torch.compile's freezing path emits, without its compile time (measured: no faster than this);
* bf16 on CPUs with native bf16 (AVX512-BF16 / AMX) when precision is "auto" or "bf16", keeping argmax
  decisions identical to fp32 on our benchmark set (docs/benchmarks.md) by two precautions: the input and
  the first layer's weights are split into a bf16 high part and a bf16 residual (x ≈ hi + lo, three bf16
  products, ≈16-bit mantissa where quantisation of the raw image hurts most), and the 1×1 heads run in
  fp32 so the Q map is not rounded to bf16's 8-bit mantissa (which alone flipped ~6 % of argmaxes).

The int8 form (common/int8net.py) reuses these layers for what it keeps in fp32.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .model import GRConvNet

_FUSED_OPS = ("_convolution_pointwise", "_convolution_pointwise_", "_convolution_transpose_pointwise",
              "_reorder_convolution_weight", "_reorder_convolution_transpose_weight")


def fused_ops_available() -> bool:
    """Whether this PyTorch build has oneDNN's prepacked, fused convolution ops."""
    if not torch.backends.mkldnn.is_available():
        return False
    return all(hasattr(torch.ops.mkldnn, name) for name in _FUSED_OPS)


def _fold(conv: torch.nn.Module, bn: torch.nn.BatchNorm2d, transposed: bool = False,
          weight_dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """Weights and bias of conv followed by eval-mode BN as one conv (out channels: dim 0, or 1 if transposed).

    weight_dtype: the conv weight is rounded to it first. bf16 makes what the engine uses a function of the
    bf16 weights alone, so weights sent in bf16 (common/weights_wire.py) give the same bits as fp32 ones.
    """
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    shape = (1, -1, 1, 1) if transposed else (-1, 1, 1, 1)
    weight = conv.weight.to(weight_dtype).float()
    return weight * scale.view(shape), (conv.bias - bn.running_mean) * scale + bn.bias


class _Layer:
    """One (transposed) convolution with folded weights, run by oneDNN's fused op or by plain aten."""

    def __init__(self, weight: Tensor, bias: Tensor, dtype: torch.dtype, stride: int, padding: int,
                 transposed: bool, fused: bool):
        self.weight = weight.detach().to(dtype).contiguous(memory_format=torch.channels_last)
        self.bias = bias.detach().to(dtype)
        self.stride, self.padding, self.transposed, self.fused = [stride] * 2, [padding] * 2, transposed, fused
        self.packed: Tensor | None = None
        self.packed_for: tuple[int, ...] | None = None

    def _packed_weight(self, x: Tensor) -> Tensor:
        # oneDNN picks the weight layout for an input shape; repack if the shape changes (rare: ~ms).
        if self.packed_for != tuple(x.shape):
            w, size, mk = self.weight.contiguous(), list(x.shape), torch.ops.mkldnn
            if self.transposed:
                self.packed = mk._reorder_convolution_transpose_weight(w, self.padding, [0, 0], self.stride,
                                                                       [1, 1], 1, size)
            else:
                self.packed = mk._reorder_convolution_weight(w, self.padding, self.stride, [1, 1], 1, size)
            self.packed_for = tuple(x.shape)
        return self.packed

    def __call__(self, x: Tensor, relu: bool = True, add_to: Tensor | None = None) -> Tensor:
        """conv(x) [+ add_to, in place] [then ReLU]; `add_to` and `relu` are not combined here."""
        if self.fused:
            mk, w = torch.ops.mkldnn, self._packed_weight(x)
            if add_to is not None:
                return mk._convolution_pointwise_.binary(add_to, x, w, self.bias, self.padding, self.stride,
                                                         [1, 1], 1, "add", 1.0, None, [None], None)
            act = "relu" if relu else "none"
            if self.transposed:
                return mk._convolution_transpose_pointwise(x, w, self.bias, self.padding, [0, 0], self.stride,
                                                           [1, 1], 1, act, [None], "")
            return mk._convolution_pointwise(x, w, self.bias, self.padding, self.stride, [1, 1], 1, act,
                                             [None], "")
        conv = F.conv_transpose2d if self.transposed else F.conv2d
        y = conv(x, self.weight, self.bias, stride=self.stride, padding=self.padding)
        if add_to is not None:
            return add_to.add_(y)
        return y.relu_() if relu else y


class FastNet:
    """Inference-only form of one GRConvNet: (B,4,H,W) fp32 → (B,H,W,K+R) fp32 = (K Q channels, R rotation
    channels); K = 1 but for a pick net with a Q per closing angle."""

    def __init__(self, net: GRConvNet, precision: str = "fp32", fused: bool | None = None):
        if net.training:
            raise ValueError("FastNet folds BatchNorm running statistics: build it from a net in eval mode")
        self.low_precision = precision == "bf16"
        dtype = torch.bfloat16 if self.low_precision else torch.float32
        fused = fused_ops_available() if fused is None else fused
        with torch.no_grad():
            w1, b1 = _fold(net.conv1, net.bn1)
            if self.low_precision:  # x·w ≈ hi(x)·hi(w) + lo(x)·hi(w) + hi(x)·lo(w), stacked along input channels
                w_hi = w1.to(dtype)
                w1 = torch.cat([w_hi, w_hi, (w1 - w_hi.float()).to(dtype)], 1).float()
            self.layers = [_Layer(w1, b1, dtype, 1, 4, False, fused),
                           _Layer(*_fold(net.conv2, net.bn2, False, dtype), dtype, 2, 1, False, fused),
                           _Layer(*_fold(net.conv3, net.bn3, False, dtype), dtype, 2, 1, False, fused)]
            self.res = [(_Layer(*_fold(b.conv1, b.bn1, False, dtype), dtype, 1, 1, False, fused),
                         _Layer(*_fold(b.conv2, b.bn2, False, dtype), dtype, 1, 1, False, fused))
                        for b in net.res]
            self.up = [_Layer(*_fold(net.deconv1, net.bn4, True, dtype), dtype, 2, 1, True, fused),
                       _Layer(*_fold(net.deconv2, net.bn5, True, dtype), dtype, 2, 1, True, fused)]
            self.conv6 = _Layer(net.conv6.weight, net.conv6.bias, dtype, 1, 4, False, fused)
            q_w, q_b = net.q_head.weight[:, :, 0, 0].double(), net.q_head.bias.double()
            if net.q_basis is not None:  # a Q per closing angle: the fixed harmonic basis folded in
                basis = net.q_basis.double()
                q_w, q_b = basis @ q_w, basis @ q_b
            heads_w = torch.cat([q_w.float(), net.rot_head.weight[:, :, 0, 0]], 0)
            self.heads_w = heads_w.detach().float().t().contiguous()  # (C, Q + rotation channels)
            self.heads_b = torch.cat([q_b.float(), net.rot_head.bias]).detach().float()
            self.outputs = int(self.heads_b.numel())
            self.q_channels = int(q_w.shape[0])

    def __call__(self, x: Tensor) -> Tensor:
        return self.tail(self.trunk(x))

    def trunk(self, x: Tensor) -> Tensor:
        """(B,4,H,W) fp32 input → the (B,C,H,W) channels_last features conv6 reads."""
        if self.low_precision:
            hi = x.to(torch.bfloat16)
            x = torch.cat([hi, (x - hi.float()).to(torch.bfloat16), hi], 1)
        x = x.contiguous(memory_format=torch.channels_last)
        for layer in self.layers:
            x = layer(x)
        for first, second in self.res:
            x = second(first(x), add_to=x)
        for layer in self.up:
            x = layer(x)
        return x

    def tail(self, x: Tensor) -> Tensor:
        """conv6 then the 1x1 heads (one fp32 addmm): (B,C,H,W) features → (B,H,W,K+R)."""
        x = self.conv6(x, relu=False)
        b, c, h, w = x.shape
        rows = x.permute(0, 2, 3, 1).reshape(-1, c).float()  # a view for channels_last
        return torch.addmm(self.heads_b, rows, self.heads_w).view(b, h, w, self.outputs)
