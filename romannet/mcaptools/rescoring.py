"""Re-scoring a recorded step from its depth heightmaps: X, P and R_tp under another reward configuration.

Pure functions (`romannet mcap rescore` applies them to episode files). P and R_tp follow the episode
rules the simulator and a real robot apply (common.episode_rules: clutter and arrangement by the occupied
footprint relative to the episode's first heightmap, stacking by the stack height in cubes over the goal),
so with the recorded configuration they reproduce the recorded P. X is judged per primitive from the two
depth heightmaps, or taken as recorded:

* push: at least `push_min_area_m2` of the workspace changed height by more than `changed_height_m` (an
  object was perturbed; the simulator asks for an object moved by > 1 cm);
* pick: the occupied footprint shrank by at least `pick_min_area_m2` (an object left the scene: removed
  in clutter, lifted out of view while held in stacking). A heightmap cannot tell a grasp from an object
  knocked over or out of the workspace, so this is the least reliable of the three (docs/recording.md
  has the measured agreement with the simulator's own X);
* place: the stack measured on the heightmap grew (exactly the simulator's rule).

`source` picks: "auto" (default) push and place from the heightmaps, pick as the robot recorded it (its
finger gap after closing); "heightmap" all three from the heightmaps; "recorded" all as recorded.

R_tp = W(primitive) * X * P_after, 0 when progress reversed (common.episode_rules.step_reward). The
Gaussian of TPG is applied by the learner when it builds labels, from its own [reward] section.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from romannet.common.config import RewardConfig, TaskConfig
from romannet.common.configbase import require
from romannet.common.episode_rules import occupied_pixels, step_reward, task_progress
from romannet.common.stack import stack_height


@dataclass(frozen=True)
class SuccessRule:
    """How X is judged when re-scoring (see the module docstring)."""

    source: Literal["auto", "heightmap", "recorded"] = "auto"
    changed_height_m: float = 0.01  # a pixel changed when its height moved by more than this
    push_min_area_m2: float = 5e-4  # push: at least this area changed height (5 cm^2)
    pick_min_area_m2: float = 3e-4  # pick: the occupied footprint shrank by at least this (3 cm^2)

    def __post_init__(self) -> None:
        require(self.source in ("auto", "heightmap", "recorded"), "rescore.success", self.source,
                "must be 'auto', 'heightmap' or 'recorded'")
        require(math.isfinite(self.changed_height_m) and 0.0 < self.changed_height_m < 0.2,
                "rescore.changed_height_m", self.changed_height_m, "must be in (0, 0.2) m")
        for name in ("push_min_area_m2", "pick_min_area_m2"):
            value = getattr(self, name)
            require(math.isfinite(value) and 0.0 < value < 0.1, f"rescore.{name}", value, "must be in (0, 0.1) m^2")

    def judged_from_heightmaps(self, primitive: str) -> bool:
        return self.source == "heightmap" or (self.source == "auto" and primitive != "pick")


def area_pixels(area_m2: float, resolution_m: float) -> int:
    """An area in heightmap pixels of resolution_m metres (at least 1)."""
    return max(1, math.ceil(area_m2 / resolution_m**2 - 1e-9))


@dataclass(frozen=True)
class Score:
    """X, P before and after, and R_tp of one step."""

    success: bool
    progress_before: float
    progress_after: float
    reward: float


def _finite(depth_hm: np.ndarray) -> np.ndarray:
    return np.nan_to_num(np.asarray(depth_hm, np.float32), nan=0.0, posinf=0.0, neginf=0.0)


def changed_pixels(depth_before: np.ndarray, depth_after: np.ndarray, changed_height_m: float) -> int:
    """Pixels whose height moved by more than changed_height_m between the two heightmaps."""
    return int(np.count_nonzero(np.abs(_finite(depth_after) - _finite(depth_before)) > changed_height_m))


def heightmap_success(primitive: str, depth_before: np.ndarray, depth_after: np.ndarray, rule: SuccessRule,
                      resolution_m: float, occupied_height_m: float, cube_size_m: float) -> bool:
    """X judged from the depth heightmaps before and after the action (see the module docstring)."""
    if primitive == "push":
        changed = changed_pixels(depth_before, depth_after, rule.changed_height_m)
        return changed >= area_pixels(rule.push_min_area_m2, resolution_m)
    if primitive == "pick":
        removed = occupied_pixels(depth_before, occupied_height_m) - occupied_pixels(depth_after, occupied_height_m)
        return removed >= area_pixels(rule.pick_min_area_m2, resolution_m)
    if primitive == "place":  # the stack grew: the rule every environment applies (episode_rules.judge_step)
        return stack_height(depth_after, cube_size_m) > stack_height(depth_before, cube_size_m)
    raise ValueError(f"primitive = {primitive!r} must be push, pick or place")


def rescore_step(primitive: str, recorded_success: bool, depth_before: np.ndarray, depth_after: np.ndarray,
                 depth_start: np.ndarray, task: TaskConfig, reward: RewardConfig, rule: SuccessRule,
                 resolution_m: float) -> Score:
    """X, P and R_tp of one recorded step under `reward` (depths: metres above the floor, h x w)."""
    if rule.judged_from_heightmaps(primitive):
        success = heightmap_success(primitive, depth_before, depth_after, rule, resolution_m,
                                    reward.occupied_height_m, task.cube_size_m)
    else:
        success = bool(recorded_success)
    p_before = task_progress(depth_before, depth_start, task, reward)
    p_after = task_progress(depth_after, depth_start, task, reward)
    return Score(success, p_before, p_after, step_reward(primitive, success, p_before, p_after, reward))
