"""`romannet bench inference --json`: the actor's decision latency against two baselines, in one run.

* decision_ms: the actor's path at 224×224 while not holding — preprocess, PushNet + PickNet through the
  InferenceEngine, angle decoding and argmax selection (explore_rate 0), with the paper's rotation head
  (model.rotation_harmonics = 1).
* decision_harmonics2_ms: the same path with the two-harmonic rotation head
  (model.rotation_harmonics = 2: 5 output channels per net instead of 3, and the two-candidate decode);
  harmonics2_vs_decision is its ratio to decision_ms.
* decision_clearance_ms: the same decision with the pick clearance rule (exploration.pick_clearance; the RG2's
  footprint, common/grasp_clearance.py); clearance_vs_decision is its ratio to decision_ms.
* decision_angle_bins_ms: the decision with the clearance rule and a pick Q per closing angle
  (model.pick_angle_bins = 16: 16 Q channels from one pass, the best clear angle per pixel);
  angle_bins_vs_clearance is its ratio to decision_clearance_ms.
* naive_fp32_all_nets_ms: eager fp32 forward of all three nets (plain nn.Module, NCHW, inference mode).
* rotations16_ms: the authors' approach — the three nets over 16 rotated 320×320 copies of the padded
  input (affine_grid / grid_sample, nearest, as in their code), outputs rotated back, then an argmax.
* decision_agreement: share of identical (primitive, row, col) choices between the fast path and the fp32
  reference on seeded synthetic heightmaps with blocks (random-init weights with a fixed seed).
* precisions: the same decision with every precision this machine runs (fp32, bf16, int8): latency, ratio to
  the naive pass and to the 16 rotations, agreement, mean latency over the agreement inputs, the cost of
  load_state, and for int8 the share of decisions rerun in fp32 as near ties and the agreement without them.
  The top-level decision fields are the precision "auto" picks here.

Timings interleave the measurements repeat by repeat, so the ratios compare the same machine state
(a shared machine drifts from minute to minute); medians are reported, minima beside them.
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F

from romannet.common.config import ExplorationConfig, ModelConfig
from romannet.common.grasp_clearance import GripperFootprint, PickClearance
from romannet.common.int8net import Int8Net, int8_ops_available
from romannet.common.model import RoManNet, parameter_count, preprocess, state_dict_to_tensors
from romannet.common.policy import (
    FastNet,
    InferenceEngine,
    cpu_bf16_flags,
    decide,
    fused_ops_available,
    native_bf16,
    nets_to_run,
    resolve_inference_precision,
    weight_bits_here,
)
from romannet.common.scenes import SIZE_PX, synthetic_scene
from romannet.info import cpu_model

from .inference_agreement import agreement, first_line, precision_engines, shipped_models_agreement

logger = logging.getLogger(__name__)

# What limits the instruction sets of oneDNN, ATen and FBGEMM (to emulate an older CPU); recorded when set.
ISA_LIMIT_VARIABLES = ("ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY", "FBGEMM_ENABLE_INSTRUCTIONS")
ROTATED_SIZE_PX = 320  # the authors pad the 224 heightmap so that every rotation of it fits
NUM_ROTATIONS = 16


def _rotation_grid(theta: float, size: tuple[int, int, int, int]) -> torch.Tensor:
    mat = torch.tensor([[math.cos(theta), math.sin(theta), 0.0], [-math.sin(theta), math.cos(theta), 0.0]])
    return F.affine_grid(mat[None], list(size), align_corners=False)


def rotations16_decision(model: RoManNet, color_hm: np.ndarray, depth_hm: np.ndarray) -> tuple[int, int, int, int]:
    """The authors' way: every net on 16 rotated copies, outputs rotated back; argmax (net, rotation, r, c)."""
    pad = (ROTATED_SIZE_PX - color_hm.shape[0]) // 2
    x = F.pad(preprocess(color_hm, depth_hm), (pad, pad, pad, pad))
    best, best_idx = -math.inf, (0, 0, 0, 0)
    with torch.inference_mode():
        for r in range(NUM_ROTATIONS):
            theta = 2 * math.pi * r / NUM_ROTATIONS
            rotated = F.grid_sample(x, _rotation_grid(-theta, x.shape), mode="nearest", align_corners=False)
            for n, net in enumerate(model.nets.values()):
                q, _ = net(rotated)
                back = F.grid_sample(q[:, None], _rotation_grid(theta, (1, 1) + q.shape[-2:]), mode="nearest",
                                     align_corners=False)[0, 0, pad:-pad, pad:-pad]
                value, flat = torch.max(back.flatten(), 0)
                if float(value) > best:
                    best, best_idx = float(value), (n, r) + divmod(int(flat), back.shape[1])
    return best_idx


def _time_ms(fn: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1e3


def _summary(samples: list[float]) -> tuple[float, float]:
    return round(statistics.median(samples), 2), round(min(samples), 2)


def _ablation(engine: InferenceEngine, x: torch.Tensor, repeats: int) -> dict[str, dict]:
    """PushNet + PickNet forward only (no selection), one optimisation added at a time: median and min ms.

    The minimum is the better guide to what each step buys on an idle machine; the median shows how it
    holds up when other processes share the two cores.
    """
    model = engine.model
    nets = [model.nets["push"], model.nets["pick"]]
    x_cl = x.contiguous(memory_format=torch.channels_last)
    model_cl = RoManNet(model.cfg).eval()
    model_cl.load_state_dict(model.state_dict())
    model_cl = model_cl.to(memory_format=torch.channels_last)
    nets_cl = [model_cl.nets["push"], model_cl.nets["pick"]]

    def autocast_cl() -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            for n in nets_cl:
                n(x_cl)

    variants: dict[str, Callable[[], object]] = {
        "eager_fp32": lambda: [n(x) for n in nets],
        "eager_fp32_channels_last": lambda: [n(x_cl) for n in nets_cl],
        "autocast_bf16_channels_last": autocast_cl,
    }
    unsupported: dict[str, str] = {}  # variants this CPU cannot run (oneDNN's bf16 kernels need AVX-512 or AVX-NE)
    for precision in ("fp32", "bf16"):
        for fused in ((False, True) if fused_ops_available() else (False,)):
            name = f"folded_{precision}{'_fused_prepacked' if fused else ''}"
            try:
                fast = [FastNet(n, precision, fused) for n in nets]
            except RuntimeError as err:
                unsupported[name] = first_line(err)
                continue
            variants[name] = lambda fast=fast: [f(x) for f in fast]
    if int8_ops_available():  # the int8 trunk, fp32 first conv, transposed convs and folded heads
        int8 = [Int8Net(n, fused_ops_available(), weight_bits_here()) for n in nets]
        variants["int8_trunk_fused_prepacked"] = lambda: [f(x) for f in int8]
    if engine.parallel_nets:
        variants[f"engine_{engine.precision}_parallel_nets"] = lambda: engine.forward(x, ("push", "pick"))
    with torch.inference_mode():
        for name, fn in list(variants.items()):
            try:
                fn()  # warm-up: oneDNN primitive creation
            except RuntimeError as err:
                unsupported[name] = first_line(err)
                del variants[name]
        samples: dict[str, list[float]] = {k: [] for k in variants}
        for _ in range(repeats):
            for name, fn in variants.items():
                samples[name].append(_time_ms(fn))
    result: dict[str, dict] = {name: dict(zip(("median_ms", "min_ms"), _summary(s), strict=True))
                               for name, s in samples.items()}
    result.update({name: {"unsupported": why} for name, why in unsupported.items()})
    return result


def _load_state_ms(engine: InferenceEngine, x: torch.Tensor, repeats: int = 3) -> tuple[float, float]:
    """Median ms of load_state (fold, quantise) and of the first forward after it (prepacks) minus a second."""
    tensors = state_dict_to_tensors(engine.model)
    loads, firsts = [], []
    for _ in range(repeats):
        loads.append(_time_ms(lambda: engine.load_state(tensors)))
        first = _time_ms(lambda: engine.forward(x, ("push", "pick")))
        firsts.append(first - _time_ms(lambda: engine.forward(x, ("push", "pick"))))
    return round(statistics.median(loads), 1), round(statistics.median(firsts), 1)


def _with_cost_ratios(by_weights: dict[str, dict], naive_ms: float) -> dict[str, dict]:
    """Each precision's mean decision over the agreement inputs (near-tie reruns included) over the naive pass."""
    return {weights: {p: ({**r, "decision_mean_vs_naive": round(r["decision_mean_ms"] / naive_ms, 4)}
                          if "decision_mean_ms" in r else r) for p, r in per.items()} if "left_out" not in per
            else per for weights, per in by_weights.items()}


def run_inference_benchmark(repeats: int = 30, seed: int = 0, agreement_inputs: int = 100,
                            rotation_repeats: int = 1, ablation: bool = True, trained: bool = True) -> dict:
    """Measure the decision path against the naive and rotation baselines; returns one JSON-able dict.

    The top-level decision fields are the engine that precision "auto" gives on this machine; `precisions`
    has every precision this machine runs, timed in the same rounds (bf16 where it is not native: a few
    rounds and no agreement, as it is ~12x slower than fp32 there)."""
    if repeats < 1 or agreement_inputs < 1 or rotation_repeats < 1:
        raise ValueError("repeats, agreement_inputs and rotation_repeats must be >= 1")
    started = time.perf_counter()
    # The paper's rotation head (one harmonic), the baseline of decision_harmonics2_ms.
    cfg = ModelConfig(rotation_harmonics=1)
    model = RoManNet(cfg, seed=seed).eval()
    engines, left_out = precision_engines(model, cfg)
    auto = resolve_inference_precision(cfg.precision)
    engine = engines[auto]
    slow = {p for p in engines if p == "bf16" and not native_bf16()}
    exploration = ExplorationConfig()
    primitives = ("push", "pick")
    scene_rng = np.random.default_rng(seed)
    color, depth = synthetic_scene(scene_rng)
    x = preprocess(color, depth)
    rng = np.random.default_rng(seed)

    def decision_by(e: InferenceEngine) -> Callable[[], object]:
        return lambda: decide(e, color, depth, False, 0.0, rng, primitives, exploration)

    clearance = PickClearance(GripperFootprint(travel_m=0.055, pick_depth_m=0.03, tip_floor_m=0.006), 0.002)

    def decision_clearance() -> object:
        return decide(engine, color, depth, False, 0.0, rng, primitives, exploration, clearance=clearance)

    # A pick Q per closing angle (model.pick_angle_bins = 16), with the clearance rule on the same 16 angles.
    cfg_bins = replace(cfg, pick_angle_bins=16)
    engine_bins = InferenceEngine(RoManNet(cfg_bins, seed=seed).eval(), cfg_bins)

    def decision_angle_bins() -> object:
        return decide(engine_bins, color, depth, False, 0.0, rng, primitives, exploration, clearance=clearance)

    def decision_exploring() -> object:
        return decide(engine, color, depth, False, 1.0, rng, primitives, exploration)

    # The two-harmonic rotation head (model.rotation_harmonics = 2: 5 output channels instead of 3).
    cfg2 = replace(cfg, rotation_harmonics=2)
    engine2 = InferenceEngine(RoManNet(cfg2, seed=seed).eval(), cfg2)

    def naive() -> None:
        with torch.inference_mode():
            for net in model.nets.values():
                net(x)

    timed: dict[str, Callable[[], object]] = {"naive": naive, "explore": decision_exploring,
                                              "harmonics2": decision_by(engine2), "clearance": decision_clearance,
                                              "angle_bins": decision_angle_bins}
    timed.update((f"decision_{p}", decision_by(e)) for p, e in engines.items() if p not in slow)
    for fn in timed.values():
        fn()  # warm-up
    samples: dict[str, list[float]] = {k: [] for k in timed}
    for _ in range(repeats):
        for name, fn in timed.items():
            samples[name].append(_time_ms(fn))
    for p in slow:  # emulated bf16: a few rounds of its own, beside the naive pass
        fn = decision_by(engines[p])
        fn()
        for _ in range(min(3, repeats)):
            samples["naive"].append(_time_ms(naive))
            samples.setdefault(f"decision_{p}", []).append(_time_ms(fn))
    rotation_samples = [_time_ms(lambda: rotations16_decision(model, color, depth)) for _ in range(rotation_repeats)]

    scenes = [synthetic_scene(scene_rng) for _ in range(agreement_inputs)]
    measured = tuple(p for p in engines if p not in slow)
    agreement_by_weights = {"random-init": agreement({p: engines[p] for p in measured}, model, scenes, rng,
                                                     primitives, exploration)}
    if trained:
        agreement_by_weights.update(shipped_models_agreement(measured, scenes, seed, exploration, primitives))
    agreement_random = agreement_by_weights["random-init"]

    naive_ms, naive_min = _summary(samples["naive"])
    rotations_ms = round(statistics.median(rotation_samples), 1)
    precisions: dict[str, dict] = {}
    for p, e in engines.items():
        ms, min_ms = _summary(samples[f"decision_{p}"])
        load_ms, first_ms = _load_state_ms(e, x)
        precisions[p] = {"decision_ms": ms, "decision_min_ms": min_ms, "decision_vs_naive": round(ms / naive_ms, 4),
                         "rotations16_vs_decision": round(rotations_ms / ms, 1), "load_state_ms": load_ms,
                         "first_forward_after_load_extra_ms": first_ms, "emulated": p in slow,
                         **agreement_random.get(p, {"agreement": None})}
    precisions.update((p, {"left_out": why}) for p, why in left_out.items())
    decision_ms, decision_min = precisions[auto]["decision_ms"], precisions[auto]["decision_min_ms"]
    result = {
        "decision_ms": decision_ms,
        "decision_min_ms": decision_min,
        "decision_exploring_ms": _summary(samples["explore"])[0],
        "decision_harmonics2_ms": _summary(samples["harmonics2"])[0],
        "harmonics2_vs_decision": round(_summary(samples["harmonics2"])[0] / decision_ms, 3),
        "decision_clearance_ms": _summary(samples["clearance"])[0],
        "clearance_vs_decision": round(_summary(samples["clearance"])[0] / decision_ms, 3),
        "decision_angle_bins_ms": _summary(samples["angle_bins"])[0],
        "angle_bins_vs_clearance": round(_summary(samples["angle_bins"])[0] / _summary(samples["clearance"])[0], 3),
        "naive_fp32_all_nets_ms": naive_ms,
        "naive_fp32_all_nets_min_ms": naive_min,
        "rotations16_ms": rotations_ms,
        "decision_vs_naive": round(decision_ms / naive_ms, 4),
        "rotations16_vs_decision": round(rotations_ms / decision_ms, 1),
        "decision_agreement": precisions[auto]["agreement"],
        "agreement_inputs": agreement_inputs,
        "agreement_by_weights": _with_cost_ratios(agreement_by_weights, naive_ms),
        "precisions": precisions,
        "nets_in_decision": list(nets_to_run(False, primitives)),
        "parameters_per_net": {name: parameter_count(net) for name, net in model.nets.items()},
        "precision": engine.precision,
        "parallel_nets": engine.parallel_nets,
        "fused_prepacked_ops": engine.fused,
        "channels_last": True,
        "torch_compile": False,
        "cpu_bf16_flags": list(cpu_bf16_flags()),
        "native_bf16": native_bf16(),
        "int8_ops": int8_ops_available(),
        "isa_limits": {k: v for k in ISA_LIMIT_VARIABLES if (v := os.environ.get(k))},
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "repeats": repeats,
        "rotation_repeats": rotation_repeats,
        "size_px": [SIZE_PX, SIZE_PX],
        "machine": f"{platform.machine()} {platform.processor() or ''} {cpu_model()}".strip(),
        "date": datetime.date.today().isoformat(),
    }
    if ablation:
        result["forward_push_pick_ms"] = _ablation(engine, x, max(3, repeats // 6))
    for e in (*engines.values(), engine2):
        e.close()
    result["benchmark_s"] = round(time.perf_counter() - started, 1)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m romannet.bench.inference", description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--agreement-inputs", type=int, default=100)
    p.add_argument("--no-ablation", action="store_true")
    p.add_argument("--no-trained", action="store_true", help="agreement on random-init nets only, not models/*")
    p.add_argument("--json", action="store_true", help="compact JSON on one line")
    args = p.parse_args(argv)
    result = run_inference_benchmark(args.repeats, args.seed, args.agreement_inputs, ablation=not args.no_ablation,
                                     trained=not args.no_trained)
    sys.stdout.write(json.dumps(result, indent=None if args.json else 2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
