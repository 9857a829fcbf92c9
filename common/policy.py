"""The actor's decision: run only the nets that can be chosen, then select an action from their maps.

`decide` accepts either a plain `RoManNet` (the fp32 eager reference, e.g. for evaluation and tests) or an
`InferenceEngine`, the actor's fast path. The engine runs an inference-only copy of each net:

* BatchNorm folded into the preceding (transposed) convolution, so a conv + bias + ReLU is one call;
* channels_last activations and, where the PyTorch build has oneDNN's fused ops, weights prepacked once
  (`mkldnn._reorder_convolution_weight`) and convolutions fused with ReLU / the residual add — the same
  kernels torch.compile's freezing path emits, without its compile time (measured: no faster than this);
* bf16 on CPUs with native bf16 (AVX512-BF16 / AMX) when precision is "auto" or "bf16", keeping argmax
  decisions identical to fp32 on our benchmark set (docs/benchmarks.md) by two precautions: the input and
  the first layer's weights are split into a bf16 high part and a bf16 residual (x ≈ hi + lo, three bf16
  products, ≈16-bit mantissa where quantisation of the raw image hurts most), and the 1×1 heads run in
  fp32 so the Q map is not rounded to bf16's 8-bit mantissa (which alone flipped ~6 % of argmaxes).

Selection (argmax, or exploration over candidates) lives in `exploration.select_action`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .action import Action
from .action_mask import action_masks, masked_q
from .config import ExplorationConfig, ModelConfig
from .exploration import select_action
from .failure_memory import FailureMemory, join_masks
from .model import GRConvNet, RoManNet, decode_rotation, load_tensors, preprocess

logger = logging.getLogger(__name__)

BF16_CPU_FLAGS = ("avx512_bf16", "amx_bf16")
_FUSED_OPS = ("_convolution_pointwise", "_convolution_pointwise_", "_convolution_transpose_pointwise",
              "_reorder_convolution_weight", "_reorder_convolution_transpose_weight")


@dataclass(frozen=True)
class PolicyMaps:
    """The maps a decision was taken from: {primitive: (h, w) float32} Q values and yaw angles (radians)."""

    q: dict[str, np.ndarray]
    angle: dict[str, np.ndarray]


def nets_to_run(holding: bool, primitives: Sequence[str]) -> tuple[str, ...]:
    """The nets whose actions can be chosen now: PlaceNet while holding, else PushNet and/or PickNet."""
    allowed = ("place",) if holding else ("push", "pick")
    nets = tuple(p for p in allowed if p in primitives)
    if not nets:
        raise ValueError(f"no primitive of {allowed} is allowed by {tuple(primitives)} "
                         f"while {'holding' if holding else 'not holding'} an object")
    return nets


@lru_cache(maxsize=1)
def cpu_bf16_flags() -> tuple[str, ...]:
    """The native-bf16 CPU flags present (from /proc/cpuinfo; empty where unreadable or absent)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    present = set(line.split(":", 1)[1].split())
                    return tuple(flag for flag in BF16_CPU_FLAGS if flag in present)
    except OSError:
        pass
    return ()


def resolve_precision(precision: str) -> str:
    """"fp32" or "bf16": "auto" picks bf16 only where the CPU computes it natively."""
    if precision == "auto":
        return "bf16" if cpu_bf16_flags() and torch.backends.mkldnn.is_available() else "fp32"
    if precision not in ("fp32", "bf16"):
        raise ValueError(f"precision {precision!r} must be 'auto', 'fp32' or 'bf16'")
    if precision == "bf16" and not cpu_bf16_flags():
        logger.warning("precision bf16 requested but the CPU has none of %s: bf16 will be emulated (slow)",
                       BF16_CPU_FLAGS)
    return precision


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
    """Inference-only form of one GRConvNet: (B,4,H,W) fp32 → (B,H,W,1+R) fp32 = (q, rotation channels...)."""

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
            heads_w = torch.cat([net.q_head.weight, net.rot_head.weight], 0)[:, :, 0, 0]
            self.heads_w = heads_w.detach().float().t().contiguous()  # (C, 1 + rotation channels)
            self.heads_b = torch.cat([net.q_head.bias, net.rot_head.bias]).detach().float()
            self.outputs = int(self.heads_b.numel())

    def __call__(self, x: Tensor) -> Tensor:
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
        x = self.conv6(x, relu=False)
        b, c, h, w = x.shape
        rows = x.permute(0, 2, 3, 1).reshape(-1, c).float()  # a view for channels_last
        return torch.addmm(self.heads_b, rows, self.heads_w).view(b, h, w, self.outputs)


class InferenceEngine:
    """The actor's fast path around a RoManNet: eval mode, inference mode, folded/prepacked nets.

    With two or more threads, nets that run in the same decision (PushNet and PickNet) run concurrently,
    each on its own share of the threads, instead of one after another on all of them: as fast on an idle
    machine and far steadier on a busy one (fewer cross-core barriers per convolution). Not thread-safe:
    one engine serves one actor loop.
    """

    def __init__(self, model: RoManNet | None = None, cfg: ModelConfig | None = None, seed: int = 0,
                 parallel_nets: bool = True):
        cfg = cfg or (model.cfg if model is not None else ModelConfig())
        self.cfg = cfg
        self.model = (model if model is not None else RoManNet(cfg, seed=seed)).eval()
        self.precision = resolve_precision(cfg.precision)
        self.fused = fused_ops_available()
        if cfg.num_threads > 0:
            torch.set_num_threads(cfg.num_threads)
        self.threads = torch.get_num_threads()
        self.parallel_nets = parallel_nets and self.threads >= 2
        self._threads_per_net = max(1, self.threads // 2)
        self._pool: ThreadPoolExecutor | None = None
        if self.parallel_nets:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="romannet-net",
                                            initializer=torch.set_num_threads,
                                            initargs=(self._threads_per_net,))
        self.nets: dict[str, FastNet] = {}
        self._rebuild()
        logger.info("inference engine: precision %s (cfg %s, cpu flags %s), fused oneDNN ops %s, %d threads%s",
                    self.precision, cfg.precision, ",".join(cpu_bf16_flags()) or "none", self.fused,
                    self.threads, f", nets in parallel on {self._threads_per_net} each" if self._pool else "")

    def _rebuild(self) -> None:
        self.nets = {name: FastNet(net, self.precision, self.fused) for name, net in self.model.nets.items()}

    def load_state(self, tensors: Mapping[str, Tensor]) -> None:
        """Swap in new weights (validated; DecodeError on mismatch) and refold them (tens of ms)."""
        load_tensors(self.model, tensors)
        self.model.eval()
        self._rebuild()

    def close(self) -> None:
        """Stop the worker thread (also done at interpreter exit)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _run(self, name: str, x: Tensor) -> Tensor:
        with torch.inference_mode():  # thread-local: the worker thread needs its own
            return self.nets[name](x)[0]

    def forward(self, x: Tensor, primitives: Sequence[str]) -> dict[str, Tensor]:
        """{primitive: (h, w, 1 + R) fp32 tensor of (q, R rotation channels)} for a (1, 4, h, w) preprocessed input."""
        names = tuple(primitives)
        if self._pool is None or len(names) < 2:
            return {p: self._run(p, x) for p in names}
        futures = {p: self._pool.submit(self._run, p, x) for p in names[1:]}
        previous = torch.get_num_threads()
        torch.set_num_threads(self._threads_per_net)  # this thread's share while the worker runs the other net
        try:
            outputs = {names[0]: self._run(names[0], x)}
        finally:
            torch.set_num_threads(previous)
        outputs.update((p, f.result()) for p, f in futures.items())
        return outputs

    def infer(self, color_hm: np.ndarray, depth_hm: np.ndarray, primitives: Sequence[str]) -> PolicyMaps:
        """Q and angle maps of the named nets only, for one heightmap pair."""
        return _to_maps(self.forward(preprocess(color_hm, depth_hm), primitives))


def _to_maps(outputs: Mapping[str, Tensor]) -> PolicyMaps:
    """{primitive: (h, w, 1 + R) tensor of (q, rotation channels)} → float32 numpy Q and decoded angle maps."""
    q, angle = {}, {}
    for p, out in outputs.items():
        arr = out.numpy()
        q[p] = np.ascontiguousarray(arr[..., 0])
        angle[p] = decode_rotation(arr[..., 1:], p).astype(np.float32, copy=False)
    return PolicyMaps(q, angle)


def reference_maps(model: RoManNet, color_hm: np.ndarray, depth_hm: np.ndarray,
                   primitives: Sequence[str]) -> PolicyMaps:
    """The named nets' maps by a plain eager fp32 forward pass in eval mode (the numerical reference)."""
    was_training = model.training
    model.eval()
    try:
        with torch.inference_mode():
            x = preprocess(color_hm, depth_hm).to(next(model.parameters()).device)
            outputs = {}
            for p in primitives:
                q, rot = model.nets[p](x)
                outputs[p] = torch.cat([q[0, ..., None], rot[0].permute(1, 2, 0)], dim=-1).float().cpu()
    finally:
        model.train(was_training)
    return _to_maps(outputs)


def decide(model: RoManNet | InferenceEngine, color_hm: np.ndarray, depth_hm: np.ndarray, holding: bool,
           explore_rate: float, rng: np.random.Generator, primitives: Sequence[str],
           exploration_cfg: ExplorationConfig, return_maps: bool = False,
           avoid: FailureMemory | None = None) -> Action | tuple[Action, PolicyMaps]:
    """Choose the next action: run the nets allowed now, then argmax or explore (prob. explore_rate).

    Holding an object only PlaceNet runs; otherwise PushNet and PickNet (PickNet only when "push" is not in
    `primitives`). avoid: the episode's failures since its last success, whose pixels are not chosen again
    (common/failure_memory.py); the returned maps leave them in, as they are the state's values, not the
    decision's. Returns the Action, or (Action, PolicyMaps) when return_maps is True.
    """
    nets = nets_to_run(holding, primitives)
    if isinstance(model, InferenceEngine):
        maps = model.infer(color_hm, depth_hm, nets)
    else:
        maps = reference_maps(model, color_hm, depth_hm, nets)
    masks = None
    if exploration_cfg.action_mask:  # masked pixels sink below every valid Q (V = max Q sees them too)
        masks = action_masks(depth_hm, nets, exploration_cfg)
        maps = PolicyMaps({p: masked_q(q, masks[p]) for p, q in maps.q.items()}, maps.angle)
    chosen_from, chosen_masks = maps.q, masks
    avoided = None if avoid is None else avoid.masks(nets, depth_hm.shape)
    if avoided is not None:
        chosen_masks = join_masks(masks, avoided)
        chosen_from = {p: masked_q(q, chosen_masks[p]) for p, q in maps.q.items()}
    action = select_action(chosen_from, maps.angle, explore_rate, exploration_cfg, rng, chosen_masks)
    return (action, maps) if return_maps else action
