"""Episode files for the MCAP tool tests, written by the real actor recorder (actor/recorder.py).

A scripted clutter episode on 32x32 heightmaps (resolution 0.014 m): blocks 3 cm high on an empty floor.
Step i is, in turn, a successful pick (the block leaves the scene), a successful push (a block moves) and
a failed pick (nothing changes). X is the script's ground truth; P and R_tp are computed with
common.episode_rules exactly as the simulator does (actor/sim/env.py), so the recorded values are what an actor
would have recorded for this scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from romannet.actor.recorder import EpisodeRecorder
from romannet.common.action import Action
from romannet.common.config import Config, load_config
from romannet.common.configbase import dumps_toml
from romannet.common.episode_rules import clutter_progress
from romannet.common.interfaces import Observation
from romannet.common.reward import progress_reversed, task_progress_reward
from romannet.common.wire import TransitionMsg, encode_transition

SIDE_PX = 32
BLOCK_PX = 4
BLOCK_M = 0.03
OVERRIDES = ["workspace.resolution_m=0.014"]


def config(run_id: str = "mcap-test") -> Config:
    return load_config(None, [*OVERRIDES, f'run_id="{run_id}"'])


def _render(blocks: list[tuple[int, int]], seed: int) -> Observation:
    rng = np.random.default_rng(seed)
    depth = np.zeros((SIDE_PX, SIDE_PX), np.float32)
    color = np.full((SIDE_PX, SIDE_PX, 3), 90, np.uint8)
    for i, (r, c) in enumerate(blocks):
        depth[r:r + BLOCK_PX, c:c + BLOCK_PX] = BLOCK_M
        color[r:r + BLOCK_PX, c:c + BLOCK_PX] = (50 + 60 * (i % 3), 200 - 40 * (i % 4), 120)
    camera = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    return Observation(color, depth, False, camera, np.full((24, 32), 0.7, np.float32))


@dataclass
class Recorded:
    """What was recorded: the file, the encoded transitions in order, and the scripted outcomes."""

    path: Path
    transitions: list[bytes] = field(default_factory=list)
    primitives: list[str] = field(default_factory=list)
    successes: list[bool] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)


def record_episode(path: Path, steps: int, actor_id: str = "a0", episode_id: str = "ep000000",
                   run_id: str = "mcap-test", seed: int = 0, finish: bool = True) -> Recorded:
    """Record a scripted episode of `steps` steps (see the module docstring); finish=False leaves the file
    as a crashed actor would (no summary, no footer)."""
    cfg = config(run_id)
    blocks = [(2 + 6 * (i % 4), 2 + 7 * (i // 4)) for i in range(steps + 1)]
    obs = _render(blocks, seed)
    depth_start = obs.depth_hm
    out = Recorded(path)
    rec = EpisodeRecorder(path, {"run_id": run_id, "actor_id": actor_id, "episode_id": episode_id,
                                 "task": "clutter", "seed": seed, "weights_version_start": 0},
                          dumps_toml(cfg), chunk_bytes=64 * 1024)
    t_ns = 1_700_000_000_000_000_000 + seed * 10**12
    rec.write_observation(obs, t_ns)
    p_before = clutter_progress(obs.depth_hm, depth_start, cfg.reward.occupied_height_m)
    for step in range(steps):
        kind = step % 3
        r, c = blocks[0]
        if kind == 0:  # pick: the block leaves the scene
            action, success, blocks = Action("pick", r + 1, c + 1, 0.5, 0.8), True, blocks[1:]
        elif kind == 1:  # push: the block slides 2 px to the right
            action, success = Action("push", r + 1, c, 0.0, 0.4, explored=True), True
            blocks = [(r, c + 2), *blocks[1:]]
        else:  # pick beside everything: nothing grasped, nothing changes
            action, success = Action("pick", SIDE_PX - 1, SIDE_PX - 1, 1.0, 0.1), False
        q_maps = {"push": np.linspace(0, 1, SIDE_PX * SIDE_PX, dtype=np.float32).reshape(SIDE_PX, SIDE_PX),
                  "pick": np.random.default_rng(step).random((SIDE_PX, SIDE_PX)).astype(np.float32)}
        start_ns = t_ns + (2 * step + 1) * 10**9
        ranges = rec.write_q_maps(q_maps, start_ns)
        after = _render(blocks, seed + step + 1)
        p_after = clutter_progress(after.depth_hm, depth_start, cfg.reward.occupied_height_m)
        reversed_ = progress_reversed(p_before, p_after, cfg.reward.progress_tolerance)
        reward = task_progress_reward(action.primitive, success, p_after, cfg.reward, reversed=reversed_)
        done = step == steps - 1
        msg = TransitionMsg(
            actor_id=actor_id, episode_id=episode_id, step=step, start_ns=start_ns, end_ns=start_ns + 10**9,
            task="clutter", color_before=obs.color_hm, depth_before=obs.depth_hm, color_after=after.color_hm,
            depth_after=after.depth_hm, action=action, success=success, progress_before=p_before,
            progress_after=p_after, reward=reward, done=done, done_reason="step_limit" if done else "",
            holding_before=False, holding_after=False, policy_version=step // 2, explore_rate=0.5,
            initial_priority=None, sim_seed=seed)
        data = encode_transition(msg)
        rec.write_observation(after, start_ns + 10**9)
        rec.write_step(data, {"step": step, "episode_id": episode_id, "primitive": action.primitive,
                              "success": success, "reward": reward, "progress_before": p_before,
                              "progress_after": p_after, "detail": "" if success else "nothing_grasped",
                              "q_ranges": ranges}, start_ns + 10**9)
        out.transitions.append(data)
        out.primitives.append(action.primitive)
        out.successes.append(success)
        out.rewards.append(reward)
        obs, p_before = after, p_after
    if finish:
        rec.close({"done_reason": "step_limit", "steps": steps, "efficiency": None, "weights_version_end": 2})
    else:  # as a writer that died here leaves it: every step's chunk, no summary, no footer
        rec._file.close()
        rec._closed = True
    return out


# A scripted stacking episode (32 x 32 px at 0.014 m, cubes 4 px wide and task.cube_size_m = 0.05 m high per
# level): (primitive, target cube or None for the bare table, explored, success); the heights change as the
# script says, and the stack height, P and R_tp are computed as the simulator computes them.
STACK_CUBES = [(2, 2), (2, 10), (2, 18), (10, 2)]
STACK_SCRIPT = [("pick", 0, False, True),  # a lone cube lifted
                ("place", 1, False, True),  # onto another: a stack of 2
                ("pick", 1, False, True),  # its top cube taken off again (progress reversed)
                ("place", 2, False, True),  # onto a third: a stack of 2 again
                ("pick", 3, False, False),  # a lone cube missed
                ("pick", None, True, False)]  # the bare table, explored


def record_stacking_episode(path: Path, run_id: str = "stack-test") -> None:
    """Record STACK_SCRIPT with the real recorder, as a stacking actor would."""
    from romannet.common.episode_rules import stacking_progress
    from romannet.common.stack import stack_height

    cfg = load_config(None, [*OVERRIDES, f'run_id="{run_id}"', 'task.kind="stacking"', "task.goal_stack_height=4"])
    cube_m, goal = cfg.task.cube_size_m, cfg.task.goal_stack_height
    levels = [1] * len(STACK_CUBES)

    def observe() -> Observation:
        depth = np.zeros((SIDE_PX, SIDE_PX), np.float32)
        for (r, c), n in zip(STACK_CUBES, levels, strict=True):
            depth[r:r + BLOCK_PX, c:c + BLOCK_PX] = n * cube_m
        return Observation(np.full((SIDE_PX, SIDE_PX, 3), 90, np.uint8), depth, False,
                           np.zeros((24, 32, 3), np.uint8), np.full((24, 32), 0.7, np.float32))

    rec = EpisodeRecorder(path, {"run_id": run_id, "actor_id": "a0", "episode_id": "ep000000", "task": "stacking",
                                 "seed": 0, "weights_version_start": 0}, dumps_toml(cfg), chunk_bytes=64 * 1024)
    t_ns = 1_700_000_000_000_000_000
    obs = observe()
    rec.write_observation(obs, t_ns)
    holding = False
    for step, (primitive, cube, explored, success) in enumerate(STACK_SCRIPT):
        r, c = STACK_CUBES[cube] if cube is not None else (SIDE_PX - 3, SIDE_PX - 3)
        if success:
            levels[cube] += 1 if primitive == "place" else -1
            holding = primitive == "pick"
        after = observe()
        p_before = stacking_progress(stack_height(obs.depth_hm, cube_m), goal)
        p_after = stacking_progress(stack_height(after.depth_hm, cube_m), goal)
        reward = task_progress_reward(primitive, success, p_after, cfg.reward,
                                      reversed=progress_reversed(p_before, p_after, cfg.reward.progress_tolerance))
        start_ns = t_ns + (2 * step + 1) * 10**9
        msg = TransitionMsg(
            actor_id="a0", episode_id="ep000000", step=step, start_ns=start_ns, end_ns=start_ns + 10**9,
            task="stacking", color_before=obs.color_hm, depth_before=obs.depth_hm, color_after=after.color_hm,
            depth_after=after.depth_hm, action=Action(primitive, r + 1, c + 1, 0.0, 0.5, explored=explored),
            success=success, progress_before=p_before, progress_after=p_after, reward=reward,
            done=step == len(STACK_SCRIPT) - 1, done_reason="step_limit" if step == len(STACK_SCRIPT) - 1 else "",
            holding_before=primitive == "place", holding_after=holding, policy_version=step, explore_rate=0.1,
            initial_priority=None, sim_seed=0)
        rec.write_observation(after, start_ns + 10**9)
        rec.write_step(encode_transition(msg), {"step": step, "episode_id": "ep000000", "primitive": primitive,
                                                "success": success, "reward": reward, "progress_before": p_before,
                                                "progress_after": p_after, "detail": "", "q_ranges": {}},
                       start_ns + 10**9)
        obs = after
    rec.close({"done_reason": "step_limit", "steps": len(STACK_SCRIPT), "efficiency": None,
               "weights_version_end": len(STACK_SCRIPT)})
