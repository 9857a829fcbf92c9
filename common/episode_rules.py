"""The rules of an episode, in one place: the simulator (actor/sim/env.py), a real robot (actor/real/env.py),
rescoring (romannet/mcaptools/rescoring.py), evaluation, the training curves and the actor's statistics all
apply these.

- refusal: an action the environment cannot attempt at all (a primitive the task does not use, a place with
  an empty hand, a push or pick while holding, a pixel outside the heightmap); it is judged a failure.
- occupied: a heightmap pixel higher than reward.occupied_height_m above the floor; a non-finite reading
  (a real camera's missing depth) counts as empty, never as occupied.
- task progress P in [0, 1]: clutter removal and arrangements 1 - occupied_now / occupied_start (the share
  of the episode's first footprint that is gone; 1 when it started empty); stacking the stack height
  measured on the heightmap (common.stack, cubes) over task.goal_stack_height.
- judging a step: X as the primitive reported it, except that a place counts only if the measured stack
  grew ("stack_not_higher"); R_tp = W X P_after, 0 when P dropped by more than reward.progress_tolerance
  (common.reward); a success ends the streak of consecutive failures.
- done reason, first that holds: "unstable", "done" (stacking: the stack reached the goal; removal: the
  scene is empty), "consecutive_failures" (sim.max_consecutive_failures), "step_limit" (sim.max_steps);
  "" while the episode goes on.
- ideal actions of a completed episode (the paper's efficiency = ideal / actual): the objects for the
  removal tasks (each picked once), 2 (h - 1) for stacking to height h (a pick and a place per added cube).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .action import Action
from .config import RewardConfig, TaskConfig
from .config_sim import SimConfig
from .reward import progress_reversed, task_progress_reward
from .stack import stack_height

TASKS = ("clutter", "arrangement", "stacking")


# ------------------------------------------------------------------------------------------ refusal
def refusal(action: Action, primitives: tuple[str, ...], holding: bool, shape_hw: tuple[int, int]) -> str:
    """Why an environment cannot attempt `action` at all ("" if it can), for a (rows, cols) heightmap."""
    if action.primitive not in primitives:
        return "primitive_not_allowed"
    if action.primitive == "place" and not holding:
        return "not_holding"
    if action.primitive != "place" and holding:
        return "holding_object"
    if not (0 <= action.row < shape_hw[0] and 0 <= action.col < shape_hw[1]):
        return "out_of_workspace"
    return ""


# ----------------------------------------------------------------------------------------- occupied
def occupied_pixels(depth_hm: np.ndarray, occupied_height_m: float) -> int:
    """Pixels of the heightmap higher than occupied_height_m (metres above the floor); non-finite: empty."""
    depth = np.asarray(depth_hm)
    if depth.ndim != 2 or depth.size == 0:
        raise ValueError(f"depth heightmap must be a non-empty 2-D array, got shape {depth.shape}")
    return int(np.count_nonzero(np.isfinite(depth) & (depth > occupied_height_m)))


def occupied_fraction(depth_hm: np.ndarray, occupied_height_m: float) -> float:
    """Share in [0, 1] of the heightmap's pixels that are occupied (see occupied_pixels)."""
    return occupied_pixels(depth_hm, occupied_height_m) / np.asarray(depth_hm).size


# ------------------------------------------------------------------------------------- task progress
def clutter_progress(depth_hm_now: np.ndarray, depth_hm_start: np.ndarray, occupied_height_m: float) -> float:
    """Clutter-removal progress P = 1 - occupied_now / occupied_start, clipped to [0, 1].

    The paper's "ratio of occupied pixels" read as the share of the episode's initial footprint that is gone.
    Clipped because spreading objects can raise the footprint above the start's; an episode that starts
    with nothing occupied is already done (P = 1). Heightmaps: metres above the floor, the same (h, w).
    """
    if np.shape(depth_hm_now) != np.shape(depth_hm_start):
        raise ValueError(f"heightmap shapes differ: now {np.shape(depth_hm_now)}, start {np.shape(depth_hm_start)}")
    if not (math.isfinite(occupied_height_m) and occupied_height_m > 0):
        raise ValueError(f"occupied_height_m = {occupied_height_m!r} must be a positive number of metres")
    occupied_start = occupied_fraction(depth_hm_start, occupied_height_m)
    if occupied_start == 0.0:
        return 1.0
    occupied_now = occupied_fraction(depth_hm_now, occupied_height_m)
    return float(np.clip(1.0 - occupied_now / occupied_start, 0.0, 1.0))


def stacking_progress(height: float, goal_height: float) -> float:
    """Stacking progress P = height / goal_height, clipped to [0, 1], both in cubes (or both in metres).

    A non-finite height (a failed measurement) raises rather than silently rewarding.
    """
    if not math.isfinite(height):
        raise ValueError(f"stack_height = {height!r} must be finite")
    if not (math.isfinite(goal_height) and goal_height > 0):
        raise ValueError(f"goal_height = {goal_height!r} must be a positive finite number")
    return float(min(max(height / goal_height, 0.0), 1.0))


def task_progress(depth_hm: np.ndarray, depth_start: np.ndarray, task: TaskConfig, reward: RewardConfig,
                  height: int | None = None) -> float:
    """P of a heightmap in the episode that started at depth_start; height: its stack height if measured."""
    if task.kind == "stacking":
        cubes = stack_height(depth_hm, task.cube_size_m) if height is None else height
        return stacking_progress(cubes, task.goal_stack_height)
    return clutter_progress(depth_hm, depth_start, reward.occupied_height_m)


@dataclass(frozen=True)
class Measure:
    """What the rules read off one heightmap, measured once per observation."""

    stack_height: int  # cubes (common.stack)
    occupied: float  # occupied share of the pixels
    progress: float  # P


def measure(depth_hm: np.ndarray, depth_start: np.ndarray, task: TaskConfig, reward: RewardConfig) -> Measure:
    """The Measure of a heightmap in the episode that started at depth_start."""
    height = stack_height(depth_hm, task.cube_size_m)
    return Measure(height, occupied_fraction(depth_hm, reward.occupied_height_m),
                   task_progress(depth_hm, depth_start, task, reward, height))


# ------------------------------------------------------------------------------------- judging a step
def step_reward(primitive: str, success: bool, p_before: float, p_after: float, reward: RewardConfig) -> float:
    """R_tp of a step: W X P_after, 0 when progress dropped by more than reward.progress_tolerance."""
    reversed_ = progress_reversed(p_before, p_after, reward.progress_tolerance)
    return task_progress_reward(primitive, success, p_after, reward, reversed=reversed_)


@dataclass(frozen=True)
class Judgement:
    """The verdict on one step: X, why it failed, P before and after, R_tp, the failure streak after it."""

    success: bool
    detail: str
    progress_before: float
    progress_after: float
    reward: float
    consecutive_failures: int


def judge_step(primitive: str, executed: bool, detail: str, before: Measure, after: Measure,
               consecutive_failures: int, reward: RewardConfig) -> Judgement:
    """Judge a step from what the primitive reported (executed, detail; a refusal: False and its reason)
    and the Measures of the observations before and after it; consecutive_failures: the streak before."""
    success = executed
    if primitive == "place" and executed:
        success = after.stack_height > before.stack_height
        detail = "" if success else "stack_not_higher"
    r = step_reward(primitive, success, before.progress, after.progress, reward)
    streak = 0 if success else consecutive_failures + 1
    return Judgement(success, detail, before.progress, after.progress, r, streak)


# ---------------------------------------------------------------------------------------- episode end
def goal_reached(task: TaskConfig, height: int, scene_empty: bool) -> bool:
    """The task is complete: stacking, a stack of task.goal_stack_height cubes; otherwise an empty scene."""
    return height >= task.goal_stack_height if task.kind == "stacking" else scene_empty


def done_reason(goal: bool, consecutive_failures: int, steps: int, limits: SimConfig, unstable: str = "") -> str:
    """Why the episode ends after this step ("" if it goes on); see the module docstring for the order."""
    if unstable:
        return "unstable"
    if goal:
        return "done"
    if consecutive_failures >= limits.max_consecutive_failures:
        return "consecutive_failures"
    if steps >= limits.max_steps:
        return "step_limit"
    return ""


def ideal_actions(task: str, num_objects: int, goal_stack_height: int) -> int:
    """The paper's ideal action count: num_objects for removal tasks, 2 (h - 1) for stacking to height h."""
    if task == "stacking":
        if goal_stack_height < 2:
            raise ValueError(f"goal stack height {goal_stack_height}: stacking needs a goal of at least 2")
        return 2 * (goal_stack_height - 1)
    if task in TASKS:
        if num_objects < 0:
            raise ValueError(f"{task} with {num_objects} objects: a count cannot be negative")
        return num_objects
    raise ValueError(f"unknown task {task!r}: expected clutter, arrangement or stacking")
