"""The actor's decision: run only the nets that can be chosen, then select an action from their maps.

`decide` accepts either a plain `RoManNet` (the fp32 eager reference, e.g. for evaluation and tests) or an
`InferenceEngine`, the actor's fast path. The engine runs an inference-only copy of each net: FastNet
(common/fastnet.py: BatchNorm folded, channels_last, prepacked oneDNN ops; fp32 or bf16) or Int8Net
(common/int8net.py: the trunk in int8, for CPUs without native bf16). `model.precision` picks between them.

Selection (argmax, or exploration over candidates) lives in `exploration.select_action`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

from .action import Action
from .config import PRIMITIVES, ExplorationConfig, ModelConfig
from .exploration import select_action
from .failure_memory import FailureMemory, masked_q
from .fastnet import FastNet, fused_ops_available
from .grasp_clearance import PickClearance, bin_angles, nearest_clear_angle
from .int8net import Int8Net, int8_ops_available, int8_weight_bits
from .model import RoManNet, decode_rotation, load_tensors, preprocess, q_channels

logger = logging.getLogger(__name__)

BF16_CPU_FLAGS = ("avx512_bf16", "amx_bf16")
INFERENCE_PRECISIONS = ("fp32", "bf16", "int8")
# A decision whose best two Q values are closer than this share of int8's error spread (max - min of each net's
# int8 Q error on a calibration scene, common/int8net.py) is rerun in fp32. The pixels that decide lie in the
# maps' top, where int8's error is smaller than its spread over a whole map: with this share int8 kept 0.99 of
# models/clutter's, 1.00 of models/stacking's and of random-init nets' decisions on the benchmark's inputs,
# rerunning 12 %, 31 % and 4 % of them (AVX2-emulated, docs/benchmarks.md).
INT8_TIE_SHARE = 0.25
# oneDNN ISA limits (ONEDNN_MAX_CPU_ISA) under which it has no native bf16, or not even AVX2.
ONEDNN_ISAS_WITHOUT_AVX2 = ("SSE41", "AVX")
ONEDNN_ISAS_WITHOUT_BF16 = ONEDNN_ISAS_WITHOUT_AVX2 + ("AVX2", "AVX2_VNNI", "AVX512_CORE", "AVX512_CORE_VNNI")


@dataclass(frozen=True)
class PolicyMaps:
    """The maps a decision was taken from: {primitive: (h, w) float32} Q values and yaw angles (radians).

    A net with a Q per closing angle (model.pick_angle_bins) has its (K, h, w) maps in q_bins; its q is their
    maximum over the angles and its angle the angle of that maximum."""

    q: dict[str, np.ndarray]
    angle: dict[str, np.ndarray]
    q_bins: dict[str, np.ndarray] = field(default_factory=dict)


def nets_to_run(holding: bool, primitives: Sequence[str]) -> tuple[str, ...]:
    """The nets whose actions can be chosen now: PlaceNet while holding, else PushNet and/or PickNet."""
    allowed = ("place",) if holding else ("push", "pick")
    nets = tuple(p for p in allowed if p in primitives)
    if not nets:
        raise ValueError(f"no primitive of {allowed} is allowed by {tuple(primitives)} "
                         f"while {'holding' if holding else 'not holding'} an object")
    return nets


@lru_cache(maxsize=1)
def cpu_flags() -> frozenset[str]:
    """The CPU's feature flags (from /proc/cpuinfo; empty where unreadable)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


def cpu_bf16_flags() -> tuple[str, ...]:
    """The native-bf16 CPU flags present (empty where unreadable or absent)."""
    present = cpu_flags()
    return tuple(flag for flag in BF16_CPU_FLAGS if flag in present)


def onednn_isa_cap() -> str:
    """oneDNN's ISA limit set in the environment (ONEDNN_MAX_CPU_ISA, e.g. "AVX2"), or "" where none is."""
    for name in ("ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA"):
        value = os.environ.get(name, "").strip().upper()
        if value and value != "ALL":
            return value
    return ""


def native_bf16() -> bool:
    """Whether oneDNN computes bf16 natively here: the CPU has the flags and no ISA limit hides them."""
    return (bool(cpu_bf16_flags()) and torch.backends.mkldnn.is_available()
            and onednn_isa_cap() not in ONEDNN_ISAS_WITHOUT_BF16)


def bf16_prepack_runs() -> bool:
    """Whether oneDNN's prepacked bf16 convolutions (the fused path) run here: they need AVX-512 (BW, VL, DQ) or
    AVX-NE-CONVERT, natively bf16 or not; elsewhere bf16 runs through plain aten convolutions (emulated, slow)."""
    flags = cpu_flags()
    has = {"avx512bw", "avx512vl", "avx512dq"} <= flags or "avx_ne_convert" in flags
    return has and onednn_isa_cap() not in ONEDNN_ISAS_WITHOUT_AVX2 + ("AVX2", "AVX2_VNNI")


def int8_wins() -> bool:
    """Whether int8 decisions beat fp32 here: oneDNN's int8 convolutions on an x86 CPU with AVX2 or more."""
    return "avx2" in cpu_flags() and int8_ops_available() and onednn_isa_cap() not in ONEDNN_ISAS_WITHOUT_AVX2


def weight_bits_here() -> int:
    """int8 weight bits oneDNN can use here without saturating (8 with VNNI, else 7; common/int8net.py)."""
    return int8_weight_bits(cpu_flags(), onednn_isa_cap())


def resolve_precision(precision: str) -> str:
    """"fp32" or "bf16" (the learner's numerics): "auto" picks bf16 only where the CPU computes it natively."""
    if precision == "auto":
        return "bf16" if native_bf16() else "fp32"
    if precision not in ("fp32", "bf16"):
        raise ValueError(f"precision {precision!r} must be 'auto', 'fp32' or 'bf16'")
    if precision == "bf16" and not native_bf16():
        logger.warning("precision bf16 requested but the CPU has none of %s (or oneDNN is limited to %s): bf16 "
                       "will be emulated (slow)", BF16_CPU_FLAGS, onednn_isa_cap() or "its default ISA")
    return precision


def resolve_inference_precision(precision: str) -> str:
    """model.precision for the actor's decisions: "fp32", "bf16" or "int8". "auto": bf16 where native, else int8
    where oneDNN runs it with AVX2 or more (on a real AVX2 CPU it keeps >= 0.99 of fp32's decisions at 0.62-0.71
    of fp32's decision time; its weight swap, 4x fp32's, is prepared while the action executes:
    docs/benchmarks.md), else fp32."""
    if precision == "auto":
        return "bf16" if native_bf16() else "int8" if int8_wins() else "fp32"
    if precision == "int8":
        if not int8_ops_available():
            raise ValueError("precision 'int8' needs oneDNN's int8 convolutions (torch.ops.onednn.qconv2d_pointwise"
                             "), which this PyTorch build or CPU lacks: use 'auto' or 'fp32'")
        if not int8_wins():
            logger.warning("precision int8 requested on a CPU without AVX2 (or with oneDNN limited to %s): "
                           "it may be slower than fp32", onednn_isa_cap())
        return precision
    if precision not in INFERENCE_PRECISIONS:
        raise ValueError(f"precision {precision!r} must be 'auto', 'fp32', 'bf16' or 'int8'")
    return resolve_precision(precision)


@dataclass(frozen=True)
class PreparedWeights:
    """New weights built into nets by InferenceEngine.prepare, not yet in use."""

    model: RoManNet
    nets: dict[str, FastNet | Int8Net]


class InferenceEngine:
    """The actor's fast path around a RoManNet: eval mode, inference mode, folded/prepacked nets.

    With precision int8, decide() reruns a decision whose best two pixels int8 cannot order (`near_ties`,
    measured per net as it is built) with the exact fp32 form of the nets they lie in; `exact_reruns` counts
    such decisions.

    With two or more threads, nets that run in the same decision (PushNet and PickNet) run concurrently,
    each on its own share of the threads, instead of one after another on all of them: as fast on an idle
    machine and far steadier on a busy one (fewer cross-core barriers per convolution). Not thread-safe:
    one engine serves one actor loop.
    """

    def __init__(self, model: RoManNet | None = None, cfg: ModelConfig | None = None, seed: int = 0,
                 parallel_nets: bool = True, primitives: Sequence[str] | None = None):
        """primitives: the nets to build and run (an actor's task's: a clutter actor never runs PlaceNet, and
        each new version's weights are prepared for the nets it runs only); None: all three."""
        cfg = cfg or (model.cfg if model is not None else ModelConfig())
        self.cfg = cfg
        self.primitives = tuple(PRIMITIVES if primitives is None else primitives)
        unknown = sorted(set(self.primitives) - set(PRIMITIVES))
        if unknown or not self.primitives:
            raise ValueError(f"primitives {list(self.primitives)} must be some of {list(PRIMITIVES)}")
        self.model = (model if model is not None else RoManNet(cfg, seed=seed)).eval()
        self.precision = resolve_inference_precision(cfg.precision)
        self.fused = fused_ops_available() and (self.precision != "bf16" or bf16_prepack_runs())
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
        self.nets: dict[str, FastNet | Int8Net] = {}
        self._spare: RoManNet | None = None  # the model the next weights are prepared into (prepare)
        self._preparer: ThreadPoolExecutor | None = None
        self.tie_share = INT8_TIE_SHARE if self.precision == "int8" else 0.0
        self.exact_reruns = 0
        self._rebuild()
        logger.info("inference engine: precision %s (cfg %s, cpu flags %s), fused oneDNN ops %s, %d threads%s",
                    self.precision, cfg.precision, ",".join(cpu_bf16_flags()) or "none", self.fused,
                    self.threads, f", nets in parallel on {self._threads_per_net} each" if self._pool else "")

    def _built(self, model: RoManNet) -> dict[str, FastNet | Int8Net]:
        if self.precision == "int8":
            bits = weight_bits_here()
            return {name: Int8Net(model.nets[name], self.fused, bits) for name in self.primitives}
        return {name: FastNet(model.nets[name], self.precision, self.fused) for name in self.primitives}

    def _rebuild(self) -> None:
        self.nets = self._built(self.model)

    def load_state(self, tensors: Mapping[str, Tensor]) -> None:
        """Swap in new weights (validated; DecodeError on mismatch) and refold them (tens of ms; int8 also
        quantises them and measures each net's int8 error: one fp32 and one int8 pass on a 64 px scene)."""
        load_tensors(self.model, tensors)
        self.model.eval()
        self._rebuild()

    @property
    def slow_swap(self) -> bool:
        """Whether a weight swap costs about a decision (int8: ~0.1 s a net, most of it measuring its int8
        error), so an actor should prepare it while an action executes (`prepare_async`)."""
        return self.precision == "int8"

    def prepare(self, tensors: Mapping[str, Tensor]) -> PreparedWeights:
        """New weights validated (DecodeError on mismatch) and built into nets of their own, leaving the ones in
        use untouched (folded fp32 weights may share storage with the model), for `install`."""
        model, self._spare = self._spare or RoManNet(self.cfg, seed=0), None
        try:
            load_tensors(model, tensors)  # validates before it copies
        except Exception:
            self._spare = model
            raise
        return PreparedWeights(model.eval(), self._built(model))

    def prepare_async(self, tensors: Mapping[str, Tensor]) -> Future[PreparedWeights]:
        """`prepare` on a background thread with one core's threads (an action's physics or a robot's motion
        runs meanwhile); the Future raises what prepare raises. One at a time: install it before the next."""
        if self._preparer is None:
            self._preparer = ThreadPoolExecutor(1, thread_name_prefix="romannet-weights",
                                                initializer=torch.set_num_threads, initargs=(1,))
        return self._preparer.submit(self.prepare, tensors)

    def install(self, prepared: PreparedWeights) -> None:
        """Act with prepared weights from now on (the previous model is kept to prepare the next ones into)."""
        self._spare, self.model, self.nets = self.model, prepared.model, prepared.nets

    def close(self) -> None:
        """Stop the worker threads (also done at interpreter exit)."""
        for pool in (self._pool, self._preparer):
            if pool is not None:
                pool.shutdown(wait=True)
        self._pool = self._preparer = None

    def _run(self, name: str, x: Tensor, exact: bool = False) -> Tensor:
        net = self.nets.get(name)
        if net is None:
            raise ValueError(f"this engine runs the nets of {list(self.primitives)}, not {name!r}")
        with torch.inference_mode():  # thread-local: the worker thread needs its own
            return (getattr(net, "exact", net) if exact else net)(x)[0]

    def forward(self, x: Tensor, primitives: Sequence[str], exact: bool = False) -> dict[str, Tensor]:
        """{primitive: (h, w, K + R) fp32 tensor of (K Q channels, R rotation channels)} for a (1, 4, h, w)
        preprocessed input.
        exact: an int8 engine's fp32 nets (others have no second form)."""
        names = tuple(primitives)
        if self._pool is None or len(names) < 2:
            return {p: self._run(p, x, exact) for p in names}
        futures = {p: self._pool.submit(self._run, p, x, exact) for p in names[1:]}
        previous = torch.get_num_threads()
        torch.set_num_threads(self._threads_per_net)  # this thread's share while the worker runs the other net
        try:
            outputs = {names[0]: self._run(names[0], x, exact)}
        finally:
            torch.set_num_threads(previous)
        outputs.update((p, f.result()) for p, f in futures.items())
        return outputs

    def infer(self, color_hm: np.ndarray, depth_hm: np.ndarray, primitives: Sequence[str],
              exact: bool = False) -> PolicyMaps:
        """Q and angle maps of the named nets only, for one heightmap pair."""
        outputs = self.forward(preprocess(color_hm, depth_hm), primitives, exact)
        return _to_maps(outputs, {p: q_channels(self.cfg, p) for p in outputs})

    def tie_tolerance(self, nets: Sequence[str]) -> float:
        """How close two Q values in these nets' int8 maps may lie and still be in either order in fp32: the
        tie share of the largest of their int8 error spreads (0 for fp32 and bf16 engines)."""
        if self.tie_share <= 0.0:
            return 0.0
        return self.tie_share * max(getattr(self.nets[p], "error_spread", 0.0) for p in nets)

    def near_ties(self, chosen: Mapping[str, np.ndarray]) -> tuple[str, ...]:
        """The nets to rerun exactly, none unless the best two Q values of the maps a choice is made from
        (masked) are closer than `tie_tolerance`: then every net whose best value is that close to the best."""
        tolerance = self.tie_tolerance(tuple(chosen))
        flat = np.concatenate([q.ravel() for q in chosen.values()])
        if tolerance <= 0.0 or flat.size < 2:
            return ()
        second, best = np.partition(flat, flat.size - 2)[-2:]
        if not best - second < tolerance:  # also for NaN: select_action rejects those maps
            return ()
        return tuple(p for p, q in chosen.items() if q.size and q.max() >= best - tolerance)


def _to_maps(outputs: Mapping[str, Tensor], channels: Mapping[str, int]) -> PolicyMaps:
    """{primitive: (h, w, K + R) tensor of (K Q channels, rotation channels)} → float32 numpy Q and angle maps;
    channels: K per primitive (1: the angle decoded from the rotation head; more: the best angle's)."""
    q, angle, q_bins = {}, {}, {}
    for p, out in outputs.items():
        arr = out.numpy()
        k = channels[p]
        if k == 1:
            q[p] = np.ascontiguousarray(arr[..., 0])
            angle[p] = decode_rotation(arr[..., 1:], p).astype(np.float32, copy=False)
        else:
            q_bins[p] = np.ascontiguousarray(np.moveaxis(arr[..., :k], -1, 0))
            q[p], angle[p] = best_bin(q_bins[p])
    return PolicyMaps(q, angle, q_bins)


def best_bin(q_bins: np.ndarray, allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(q (h, w), angle (h, w)) of a (K, h, w) Q map per closing angle: at each pixel the best of its angles
    (only the allowed ones, bool (K, h, w); -inf where none is), and that angle k pi / K."""
    values = q_bins if allowed is None else np.where(allowed, q_bins, np.float32(-np.inf))
    # max and argmax apart: numpy's max over the leading axis is vectorised, a gather by the argmax is not
    return values.max(axis=0).astype(np.float32, copy=False), bin_angles(q_bins.shape[0])[np.argmax(values, axis=0)]


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
                q = q[0, ..., None] if q.dim() == 3 else q[0].permute(1, 2, 0)
                outputs[p] = torch.cat([q, rot[0].permute(1, 2, 0)], dim=-1).float().cpu()
    finally:
        model.train(was_training)
    return _to_maps(outputs, {p: q_channels(model.cfg, p) for p in primitives})


Maps = dict[str, np.ndarray]


def with_clearance(avoided: Maps | None, clear_bins: np.ndarray | None,
                   maps: PolicyMaps) -> tuple[Maps | None, Maps, Maps]:
    """(valid pixels, Q maps, angle maps) a decision chooses from: the failure memory's pixels (avoided), and on
    the pick map only the pixels with a clear pick (clear_bins: PickClearance.clear). A pick net with one Q per
    pixel picks at the clear angle nearest its own; one with a Q per closing angle at its best clear angle. A
    pick map with no clear pixel left keeps the failure memory's pixels and the net's angles."""
    if clear_bins is None or "pick" not in maps.angle:
        return avoided, maps.q, maps.angle
    q, angles = maps.q, maps.angle
    if "pick" in maps.q_bins:
        bins = maps.q_bins["pick"]
        if bins.shape[0] != clear_bins.shape[0]:
            raise ValueError(f"the pick net has {bins.shape[0]} angle bins, the clearance rule {clear_bins.shape[0]}")
        clear = clear_bins.any(axis=0)
        best_q, best_angle = best_bin(bins, clear_bins)
        pick_q, pick_angle = np.where(clear, best_q, maps.q["pick"]), np.where(clear, best_angle, maps.angle["pick"])
    else:
        clear, pick_angle = nearest_clear_angle(maps.angle["pick"], clear_bins)
        pick_q = maps.q["pick"]
    allowed = clear if avoided is None else clear & avoided["pick"]
    if not allowed.any():
        return avoided, maps.q, maps.angle
    valid = dict(avoided) if avoided is not None else {p: np.ones(clear.shape, dtype=bool) for p in maps.q}
    valid["pick"] = allowed
    return valid, {**q, "pick": pick_q}, {**angles, "pick": pick_angle.astype(np.float32, copy=False)}


def decide(model: RoManNet | InferenceEngine, color_hm: np.ndarray, depth_hm: np.ndarray, holding: bool,
           explore_rate: float, rng: np.random.Generator, primitives: Sequence[str],
           exploration_cfg: ExplorationConfig, return_maps: bool = False,
           avoid: FailureMemory | None = None,
           clearance: PickClearance | None = None) -> Action | tuple[Action, PolicyMaps]:
    """Choose the next action: run the nets allowed now, then argmax or explore (prob. explore_rate).

    Holding an object only PlaceNet runs; otherwise PushNet and PickNet (PickNet only when "push" is not in
    `primitives`). avoid: the episode's failures since its last success, whose pixels are not chosen again
    (common/failure_memory.py); the returned maps leave them in, as they are the state's values, not the
    decision's. clearance: picks only where the open fingers and the hand come down to the grasp height, at
    the clear angle nearest the pick net's own, or its best clear angle where it has a Q per angle, or (the
    rule's `narrowest`) across the narrowest side of what it squeezes, moved (the rule's `centre`) to the middle
    of what it squeezes (common/grasp_clearance.py). Returns the
    Action, or (Action, PolicyMaps) when return_maps is True.
    """
    nets = nets_to_run(holding, primitives)
    engine = model if isinstance(model, InferenceEngine) else None
    avoided = None if avoid is None else avoid.masks(nets, depth_hm.shape)
    clear_bins = clearance.clear(depth_hm) if clearance is not None and "pick" in nets else None

    valid: dict[str, np.ndarray] | None = avoided
    angles: dict[str, np.ndarray] = {}

    def masked(raw: PolicyMaps) -> tuple[PolicyMaps, dict[str, np.ndarray]]:
        """The maps as computed, and the Q maps the decision chooses from (the avoided and unclear pixels sunk)."""
        nonlocal valid, angles
        valid, q, angles = with_clearance(avoided, clear_bins, raw)
        chosen = q if valid is None else {p: masked_q(m, valid[p]) for p, m in q.items()}
        return raw, chosen

    if engine is None:
        maps, chosen_from = masked(reference_maps(model, color_hm, depth_hm, nets))
    else:
        raw = engine.infer(color_hm, depth_hm, nets)
        maps, chosen_from = masked(raw)
        rerun = engine.near_ties(chosen_from)
        if rerun:  # int8 cannot order the best two pixels: the fp32 nets they lie in decide
            engine.exact_reruns += 1
            exact = engine.infer(color_hm, depth_hm, rerun, exact=True)
            maps, chosen_from = masked(PolicyMaps({**raw.q, **exact.q}, {**raw.angle, **exact.angle},
                                                  {**raw.q_bins, **exact.q_bins}))
    action = select_action(chosen_from, angles, explore_rate, exploration_cfg, rng, valid)
    if clear_bins is not None and action.primitive == "pick" and (clearance.narrowest or clearance.centre):
        row, col, angle = clearance.executed(depth_hm, clear_bins, action.row, action.col, action.angle_rad)
        if avoided is not None and not avoided["pick"][row, col]:  # the middle failed already: not again
            row, col = action.row, action.col
        action = dataclasses.replace(action, row=row, col=col, angle_rad=angle)
    return (action, maps) if return_maps else action
