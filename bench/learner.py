"""`romannet bench learner --json`: transitions trained per second, fast settings vs the naive step, one run.

* fast: `Trainer` as configured by default — bf16 autocast (fp32 heads, master weights and loss),
  channels_last, the batch's items grouped by primitive into one forward pass per net, a 128 px window
  around each executed pixel, V(s_t+1) from the actor's next decision (sent with the item) — at each
  batch size.
* full_head per batch size: the fast step with the last 9x9 conv and the heads on the whole window instead of
  only the loss's region (learner.head_crop off); `fast_vs_full_head` is their ratio.
* whole_map per batch size: the same with the whole 224 px heightmap and V(s_t+1) by a forward pass here
  (the step before windows and actor values); `fast_vs_whole_map` is their ratio.
* naive_fp32_b1: the paper's literal schedule done plainly — eager fp32, NCHW, one transition per update.
* naive_fp32 per batch size: eager fp32 NCHW with the same grouping, to separate what batching buys from
  what the numerics buy.

The batches are 224x224 synthetic clutter scenes (bench.inference.synthetic_scene), half successful picks
that bootstrap V(s_t+1) through PushNet and PickNet, half failed pushes that do not: the mix a learner sees
early on. Measurements interleave repeat by repeat (a shared machine drifts from minute to minute); medians of
transitions/s are reported, ratios are taken within the run.
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import platform
import statistics
import sys
import time

import numpy as np
import torch

from romannet.common.action import Action
from romannet.common.config import ModelConfig, RewardConfig, TaskConfig
from romannet.common.config_learner import LearnerConfig
from romannet.common.policy import cpu_bf16_flags
from romannet.common.wire_messages import TransitionMsg
from romannet.info import cpu_model
from romannet.learner.trainer import BatchItem, Trainer

from .inference import SIZE_PX, synthetic_scene

logger = logging.getLogger(__name__)
TARGET_RATIO = 2.0  # issue 5: fast >= 2x the naive eager fp32 rate


def synthetic_items(n: int, rng: np.random.Generator, size_px: int = SIZE_PX) -> list[BatchItem]:
    """n training items on synthetic scenes: even indices successful picks (bootstrap), odd failed pushes."""
    items = []
    for i in range(n):
        color, depth = synthetic_scene(rng, size_px, size_px)
        color2, depth2 = synthetic_scene(rng, size_px, size_px)
        success = i % 2 == 0
        row, col = (int(v) for v in rng.integers(0, size_px, 2))
        action = Action("pick" if success else "push", row, col, float(rng.uniform(-1.5, 1.5)), 0.0)
        t = TransitionMsg(
            actor_id="bench", episode_id=f"ep-{i}", step=0, start_ns=0, end_ns=1, task="clutter",
            color_before=color, depth_before=depth, color_after=color2, depth_after=depth2, action=action,
            success=success, progress_before=0.0, progress_after=0.3 if success else 0.0,
            reward=0.3 if success else 0.0, done=False, done_reason="", holding_before=False,
            holding_after=False, policy_version=0, explore_rate=0.5,
            next_value=0.5 if success else None, next_value_version=0 if success else None)
        items.append((t, 1.0, i))
    return items


def _rate(trainer: Trainer, items: list[BatchItem]) -> float:
    """Transitions per second of one update on `items`."""
    start = time.perf_counter()
    trainer.train_step(items)
    return len(items) / (time.perf_counter() - start)


def run_learner_benchmark(batch_sizes: tuple[int, ...] = (1, 4, 8), repeats: int = 5, seed: int = 0,
                          device: str = "cpu", naive_per_batch: bool = True, threads: int = 0) -> dict:
    """Measure transitions trained per second; returns one JSON-able dict (see the module docstring)."""
    if repeats < 1 or not batch_sizes or min(batch_sizes) < 1:
        raise ValueError("repeats must be >= 1 and batch_sizes non-empty positive integers")
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but torch sees no CUDA device")
    if threads < 0:
        raise ValueError("threads must be >= 0 (0: torch's default, one per core)")
    if threads:  # `romannet up` gives a learner beside one actor a single thread on a 2-core box
        torch.set_num_threads(threads)
    started = time.perf_counter()
    model_cfg, reward_cfg, task_cfg = ModelConfig(), RewardConfig(), TaskConfig()
    fast_cfg = LearnerConfig(seed=seed)
    full_head_cfg = LearnerConfig(seed=seed, head_crop=False)
    # The step before window training and the actors' V(s_t+1): the whole heightmap, V by a forward pass here.
    today_cfg = LearnerConfig(seed=seed, train_crop_px=0, actor_value_max_age=0)
    naive_cfg = LearnerConfig(seed=seed, precision="fp32", channels_last=False, train_crop_px=0,
                              actor_value_max_age=0)
    rng = np.random.default_rng(seed)
    pool = synthetic_items(max(batch_sizes), rng)
    fast = Trainer(model_cfg, fast_cfg, reward_cfg, task_cfg, device=device)
    naive = Trainer(model_cfg, naive_cfg, reward_cfg, task_cfg, device=device)
    today = Trainer(model_cfg, today_cfg, reward_cfg, task_cfg, device=device)
    full_head = Trainer(model_cfg, full_head_cfg, reward_cfg, task_cfg, device=device)

    runs: dict[str, tuple[Trainer, list[BatchItem]]] = {"naive_fp32_b1": (naive, pool[:1])}
    for b in batch_sizes:
        runs[f"fast_b{b}"] = (fast, pool[:b])
        runs[f"full_head_b{b}"] = (full_head, pool[:b])
        runs[f"whole_map_b{b}"] = (today, pool[:b])
        if naive_per_batch and b > 1:
            runs[f"naive_fp32_b{b}"] = (naive, pool[:b])
    for trainer, items in runs.values():  # warm-up: oneDNN builds its kernels for each shape once
        trainer.train_step(items)
    samples: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, (trainer, items) in runs.items():
            samples[name].append(_rate(trainer, items))
    per_s = {name: round(statistics.median(s), 3) for name, s in samples.items()}
    naive_rate = per_s["naive_fp32_b1"]
    ratios = {f"b{b}": round(per_s[f"fast_b{b}"] / naive_rate, 2) for b in batch_sizes}
    return {
        "transitions_per_s": per_s,
        "fast_vs_naive_b1": ratios,
        "fast_vs_whole_map": {f"b{b}": round(per_s[f"fast_b{b}"] / per_s[f"whole_map_b{b}"], 2)
                              for b in batch_sizes},
        "fast_vs_full_head": {f"b{b}": round(per_s[f"fast_b{b}"] / per_s[f"full_head_b{b}"], 2)
                              for b in batch_sizes},
        "target_ratio": TARGET_RATIO,
        "target_met": {k: v >= TARGET_RATIO for k, v in ratios.items()},
        "fast_settings": {"precision": fast.precision, "channels_last": fast_cfg.channels_last,
                          "train_crop_px": fast_cfg.train_crop_px, "head_crop": fast_cfg.head_crop,
                          "actor_value_max_age": fast_cfg.actor_value_max_age,
                          "grouped_forward_per_primitive": True, "fp32_heads": True, "torch_compile": False},
        "batch_mix": "even items: successful picks (bootstrap over push+pick), odd: failed pushes",
        "model_channels": model_cfg.channels,
        "size_px": [SIZE_PX, SIZE_PX],
        "device": device,
        "threads": torch.get_num_threads(),
        "repeats": repeats,
        "cpu_bf16_flags": list(cpu_bf16_flags()),
        "torch": torch.__version__,
        "machine": f"{platform.machine()} {cpu_model()}".strip(),
        "date": datetime.date.today().isoformat(),
        "benchmark_s": round(time.perf_counter() - started, 1),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m romannet.bench.learner", description=__doc__.splitlines()[0])
    p.add_argument("--batch-sizes", default="1,4,8")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--threads", type=int, default=0, help="torch threads (default 0: one per core)")
    p.add_argument("--json", action="store_true", help="compact JSON on one line")
    args = p.parse_args(argv)
    sizes = tuple(int(b) for b in args.batch_sizes.split(",") if b.strip())
    result = run_learner_benchmark(sizes, args.repeats, args.seed, args.device, threads=args.threads)
    sys.stdout.write(json.dumps(result, indent=None if args.json else 2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
