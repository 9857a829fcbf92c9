"""The transitions `romannet bench replay` inserts: two named workloads of encoded 224x224 RGB-D transitions.

- "sim": real simulator transitions. SimEnv (clutter task, Panda arm, 10 objects) steps the scripted oracle
  for a few actions from a few seeds; each step becomes one Transition (TransitionMsg.from_step, as an
  actor builds it). Rendered clean (the
  sim's default perfect depth sensor), so the PNGs compress well: the small, common case.
- "camera_noise": synthetic tabletop scenes with camera-like noise on every pixel (sigma 3 levels of
  colour, 0.5 mm of depth), as a real RGB-D camera delivers them; noise defeats PNG compression, so these
  are ~4x larger than "sim": the heavy case the throughput target is sized for.

A workload renders/encodes a handful of distinct scenes once (nothing is cached on disk) and repeats them
under distinct (actor, episode, step) keys: only the scalar fields are re-serialised per item, so
building 2,000 payloads takes seconds, not 2,000 x 25 ms of PNG coding.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from romannet.common import romannet_pb2 as pb
from romannet.common import wire
from romannet.common.action import Action
from romannet.common.imagecodec import units_to_depth_m
from romannet.common.interfaces import Observation, StepResult

SIM_SEEDS = (0, 1, 2)
SIM_STEPS_PER_SEED = 4


def synthetic_heightmaps(seed: int, side_px: int = 224) -> tuple[np.ndarray, np.ndarray]:
    """A tabletop-like scene: grey floor, 8 coloured boxes 2-10 cm tall, camera-like noise (sigma 3 levels
    of colour, 0.5 mm of depth), so PNG sizes are realistic (random pixels would not compress at all)."""
    rng = np.random.default_rng(seed)
    color = np.full((side_px, side_px, 3), (90, 90, 95), np.float32)
    depth = np.zeros((side_px, side_px), np.float32)
    for _ in range(8):
        y, x = rng.integers(0, side_px - 30, 2)
        s = int(rng.integers(10, 30))
        color[y:y + s, x:x + s] = rng.integers(0, 256, 3)
        depth[y:y + s, x:x + s] = rng.uniform(0.02, 0.10)
    color = np.clip(color + rng.normal(0, 3, color.shape), 0, 255).astype(np.uint8)
    depth = np.clip(depth + rng.normal(0, 5e-4, depth.shape), 0, 0.6)
    return color, units_to_depth_m(np.round(depth / 1e-5).astype(np.uint16))


def camera_noise_scenes(scenes: int = 8, seed: int = 0) -> list[wire.TransitionMsg]:
    """`scenes` synthetic transitions (before and after are two different noisy scenes)."""
    out = []
    for k in range(scenes):
        before = Observation(*synthetic_heightmaps(seed + 2 * k), holding=False)
        result = StepResult(Observation(*synthetic_heightmaps(seed + 2 * k + 1), holding=True), success=True,
                            progress_before=0.1, progress_after=0.2, reward=1.0, done=False)
        out.append(wire.TransitionMsg.from_step(
            before, Action("pick", 100, 120, 0.5, 0.7, explored=False), result, actor_id=f"bench-{k}",
            episode_id="ep-0", step=0, start_ns=1, end_ns=2, task="clutter", policy_version=3, explore_rate=0.2))
    return out


def sim_scenes(seed: int = 0, seeds: int = len(SIM_SEEDS), steps: int = SIM_STEPS_PER_SEED,
               robot: str = "arm") -> list[wire.TransitionMsg]:
    """Real transitions: `steps` oracle actions in the clutter task from each of `seeds` seeds."""
    from romannet.actor.sim.env import SimEnv  # pybullet: imported only when this workload is asked for
    from romannet.actor.sim.oracle import oracle_action
    from romannet.common.config import TaskConfig
    from romannet.common.config_sim import SimConfig

    out = []
    with SimEnv(task=TaskConfig(kind="clutter"), sim=SimConfig(robot=robot)) as env:
        for episode_seed in range(seed, seed + seeds):
            obs = env.reset(episode_seed)
            for step in range(steps):
                action = oracle_action(env)
                start_ns = time.time_ns()
                result = env.step(action)
                out.append(wire.TransitionMsg.from_step(
                    obs, action, result, actor_id="bench-sim", episode_id=f"seed-{episode_seed}", step=step,
                    start_ns=start_ns, end_ns=time.time_ns(), task="clutter"))  # sim_seed: the episode's seed
                obs = result.observation
                if result.done:
                    break
    return out


# name -> builder of its distinct scenes (seed -> transitions); the order is the order they are measured in.
WORKLOADS: dict[str, Callable[[int], list[wire.TransitionMsg]]] = {
    "sim": lambda seed: sim_scenes(seed),
    "camera_noise": lambda seed: camera_noise_scenes(seed=seed),
}


def distinct_payloads(scenes: list[wire.TransitionMsg], count: int) -> list[bytes]:
    """`count` encoded transitions with distinct (actor_id, episode_id, step), cycling through `scenes`."""
    protos = []
    for msg in scenes:
        proto = pb.Transition()
        proto.ParseFromString(wire.encode_transition(msg))
        protos.append(proto)
    out = []
    for i in range(count):
        proto = protos[i % len(protos)]
        proto.actor_id, proto.episode_id, proto.step = f"bench-{i % len(protos)}", f"ep-{i // 100}", i % 100
        out.append(proto.SerializeToString())
    return out

