"""`romannet bench sim`: simulator throughput of one environment process (render + heightmap included).

Per task: actions per second with the scripted oracle and with random valid actions (a primitive the task
allows in the current holding state, a uniformly random pixel and angle), and the median milliseconds of a
render, a heightmap projection and of each primitive type (physics + IK, the observation excluded), for
the Panda arm and the floating gripper. Run it pinned to
one core (`taskset -c 0 romannet bench sim`) to read it as "per process on one core".
"""

from __future__ import annotations

import logging
import math
import statistics
import time

import numpy as np

from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.oracle import oracle_action
from romannet.common.action import Action
from romannet.common.config import TaskConfig
from romannet.common.config_sim import SimConfig

log = logging.getLogger(__name__)


def _random_action(env: SimEnv, rng: np.random.Generator) -> Action:
    allowed = [p for p in env.primitives if (p == "place") == env.holding]
    return Action(str(rng.choice(allowed)), int(rng.integers(env.ws.height_px)),
                  int(rng.integers(env.ws.width_px)), float(rng.uniform(-math.pi, math.pi)), 0.0)


def _run(env: SimEnv, policy: str, actions: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    env.reset(seed)
    step_s, episodes, successes = [], 1, 0
    prim_s: dict[str, list[float]] = {}
    for _ in range(actions):
        action = oracle_action(env) if policy == "oracle" else _random_action(env, rng)
        t0 = time.perf_counter()
        result = env.step(action)
        step_s.append(time.perf_counter() - t0)
        prim_s.setdefault(action.primitive, []).append(step_s[-1] - env.last_observe_s)
        successes += result.success
        if result.done:
            env.reset(seed + episodes)
            episodes += 1
    return {"actions_per_s": len(step_s) / sum(step_s), "median_step_ms": 1e3 * statistics.median(step_s),
            "median_primitive_ms": {k: 1e3 * statistics.median(v) for k, v in sorted(prim_s.items())},
            "success_rate": successes / len(step_s),
            "episodes": episodes}


def run_sim_benchmark(tasks: tuple[str, ...] = ("clutter", "arrangement", "stacking"), actions: int = 10,
                      seed: int = 0, num_objects: int = 10, robots: tuple[str, ...] = ("arm", "gripper")) -> dict:
    """Measure the simulator for each robot mode and task; returns one JSON-able dict (module docstring)."""
    out: dict = {"actions_per_policy": actions, "num_objects": num_objects,
                 "robots": {robot: _bench_robot(tasks, actions, seed, num_objects, robot) for robot in robots}}
    return out


def _bench_robot(tasks: tuple[str, ...], actions: int, seed: int, num_objects: int, robot: str) -> dict:
    sim = SimConfig(num_objects=num_objects, robot=robot)
    out: dict = {}
    for task in tasks:
        with SimEnv(task=TaskConfig(kind=task), sim=sim) as env:
            env.reset(seed)
            render_ms, hm_ms = [], []
            for _ in range(5):
                t0 = time.perf_counter()
                frame = env.render()  # as every step renders: the robot culled when out of view
                t1 = time.perf_counter()
                env.scene.heightmaps(frame)
                render_ms.append(1e3 * (t1 - t0))
                hm_ms.append(1e3 * (time.perf_counter() - t1))
            t0 = time.perf_counter()
            env.reset(seed)
            reset_ms = 1e3 * (time.perf_counter() - t0)
            out[task] = {
                "render_ms": statistics.median(render_ms), "heightmap_ms": statistics.median(hm_ms),
                "reset_ms": reset_ms,
                "oracle": _run(env, "oracle", actions, seed),
                "random": _run(env, "random", actions, seed),
            }
            log.info("bench sim %s %s: %s", robot, task, out[task])
    return out
