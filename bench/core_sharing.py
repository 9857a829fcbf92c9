"""A learner step loop and an actor decision loop as two processes side by side, at given thread counts.

    python -m romannet.bench.core_sharing --threads 2,2 1,1 --seconds 40 [--passive]

Each pair runs both loops for `seconds` at once and reports the mean time per learner step (batch 4, the
default Trainer on 224 px synthetic clutter items) and per actor decision (PushNet + PickNet through the
InferenceEngine): how much two processes that each assume the whole machine slow each other down
(docs/benchmarks.md, "Sharing the cores").
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time


def _loop(role: str, seconds: float) -> float:
    import numpy as np

    from romannet.common.config import ModelConfig, RewardConfig, TaskConfig
    from romannet.common.config_learner import LearnerConfig
    from romannet.common.policy import InferenceEngine
    from romannet.learner.trainer import Trainer

    from .inference import SIZE_PX, synthetic_scene
    from .learner import synthetic_items

    rng = np.random.default_rng(0)
    if role == "learner":
        trainer = Trainer(ModelConfig(), LearnerConfig(), RewardConfig(), TaskConfig())
        items = synthetic_items(4, rng)

        def call() -> None:
            trainer.train_step(items)
    else:
        engine = InferenceEngine(cfg=ModelConfig())
        color, depth = synthetic_scene(rng, SIZE_PX, SIZE_PX)

        def call() -> None:
            engine.infer(color, depth, ("push", "pick"))
    call()  # warm-up: oneDNN builds its kernels once per shape
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        call()
        n += 1
    return (time.perf_counter() - start) / n


def measure_pair(learner_threads: int, actor_threads: int, seconds: float, passive: bool) -> dict[str, float]:
    """Seconds per learner step and per actor decision, both loops running at once."""
    procs = {}
    for role, threads in (("learner", learner_threads), ("actor", actor_threads)):
        env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
        if passive:
            env["OMP_WAIT_POLICY"] = "PASSIVE"
        procs[role] = subprocess.Popen([sys.executable, "-m", "romannet.bench.core_sharing", "--role", role,
                                        "--seconds", str(seconds)], stdout=subprocess.PIPE, env=env)
    return {f"{role}_s": float(p.communicate()[0].decode().strip()) for role, p in procs.items()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", nargs="+", default=["2,2", "1,1"], metavar="LEARNER,ACTOR")
    p.add_argument("--seconds", type=float, default=40.0)
    p.add_argument("--passive", action="store_true", help="OMP_WAIT_POLICY=PASSIVE in both processes")
    p.add_argument("--role", choices=["learner", "actor"], help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.role:
        print(f"{_loop(args.role, args.seconds):.4f}")
        return 0
    out = []
    for pair in args.threads:
        lt, at = (int(v) for v in pair.split(","))
        out.append({"learner_threads": lt, "actor_threads": at, "passive": args.passive,
                    **measure_pair(lt, at, args.seconds, args.passive)})
    print(json.dumps({"pairs": out, "cpu_count": os.cpu_count(), "load_average": os.getloadavg()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
