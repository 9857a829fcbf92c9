"""The simulated tasks as Gymnasium environments, so other agents can be put on them.

Importing this module registers one id per task: "romannet/Clutter-v0", "romannet/Stacking-v0",
"romannet/Arrangement-v0" (`gymnasium.make("romannet.gym_env:romannet/Stacking-v0")` imports it itself).
Gymnasium 1.x has no plugin entry points, and `import romannet` does not import gymnasium (the CLI stays
fast), so this module is what registers them.

Spaces (h x w = the heightmap, 224 x 224 at the default 0.002 m/px; `heightmap_px=64` for speed):
  observation  Dict(color: Box(0, 255, (h, w, 3), uint8), the colour heightmap, RGB;
                    depth: Box(0, z_max - z_min, (h, w), float32), the depth heightmap, metres above the floor;
                    holding: Discrete(2), 1 while an object is in the hand (stacking only))
  action       MultiDiscrete([len(primitives), h, w, num_rotations]): (index into `primitives`, the task's
               primitives in the order ("push", "pick", "place") as enabled, row, col, angle bin); the gripper
               yaw is bin * 2 pi / num_rotations (16 by default: VPG's 22.5 degree steps) from the column axis
               toward the row axis (common.action). An action the task cannot attempt (place with an empty
               hand, pick while holding) is a failed step with reward 0, as in the fleet.
  reward       SimEnv's step reward: the paper's R_tp = W(primitive) * X * P (common.reward); the Gaussian
               spreading into R_tpg is a learner-side label map and is not part of the step.
  episode end  terminated on done_reason "done" (success), "unstable" or "consecutive_failures" (the paper's
               10 failed attempts); truncated on "step_limit" (sim.max_steps).
  info         success (the primitive's X), is_success (the task was completed), done_reason, progress (P
               after the step), detail, and SimEnv's step info.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from romannet.actor.sim.env import SimEnv
from romannet.common.action import Action
from romannet.common.config import load_config
from romannet.common.interfaces import Observation

TASKS = {"Clutter": "clutter", "Stacking": "stacking", "Arrangement": "arrangement"}
# Per-task defaults where no recipe is given (overrides still win): stacking keeps the Panda hand, as its recipe does
# (configs/experiments/stacking.toml): the scripted oracle stacks 5 cm cubes to 3 in 24 actions over 6 scenes
# with it and in 42 with the RG2 (the default hand, best on clutter).
TASK_DEFAULTS = {"stacking": ('sim.hand="panda"',)}
TERMINAL_REASONS = ("done", "unstable", "consecutive_failures")


class RoManNetEnv(gymnasium.Env[dict[str, Any], np.ndarray]):
    """One of the paper's simulated tasks (SimEnv) behind Gymnasium's API; spaces in the module docstring.

    task: "clutter" | "stacking" | "arrangement"; config: a TOML recipe (configs/...) read first;
    overrides: `section.field=value` strings as `--set` takes them, applied last (e.g. "sim.num_objects=5");
    heightmap_px: heightmap side in pixels (sets workspace.resolution_m; a multiple of 4), None keeps it.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(self, task: str = "clutter", *, config: str | Path | None = None,
                 overrides: Sequence[str] = (), heightmap_px: int | None = None,
                 num_rotations: int = 16, render_mode: str | None = None):
        if task not in TASKS.values():
            raise ValueError(f"task = {task!r} is invalid: must be one of {tuple(TASKS.values())}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode = {render_mode!r} is invalid: must be None or 'rgb_array'")
        if heightmap_px is not None and heightmap_px < 4:
            raise ValueError(f"heightmap_px = {heightmap_px} is invalid: must be a multiple of 4, >= 4")
        if num_rotations < 1:
            raise ValueError(f"num_rotations = {num_rotations} is invalid: must be >= 1")
        defaults = TASK_DEFAULTS.get(task, ()) if config is None else ()
        cfg = load_config(config, [*defaults, f'task.kind="{task}"', *overrides])
        ws = cfg.workspace
        if heightmap_px is not None:
            ws = dataclasses.replace(ws, resolution_m=(ws.x_max_m - ws.x_min_m) / heightmap_px)
        self.sim = SimEnv(ws, cfg.camera, cfg.task, cfg.reward, cfg.sim)
        self.primitives: tuple[str, ...] = self.sim.primitives
        self.num_rotations = num_rotations
        self.render_mode = render_mode
        h, w = ws.height_px, ws.width_px
        self._depth_max = np.float32(ws.z_max_m - ws.z_min_m)
        self.observation_space = spaces.Dict({
            "color": spaces.Box(0, 255, (h, w, 3), np.uint8),
            "depth": spaces.Box(np.float32(0.0), self._depth_max, (h, w), np.float32),
            "holding": spaces.Discrete(2),
        })
        self.action_space = spaces.MultiDiscrete([len(self.primitives), h, w, num_rotations])
        self._last: Observation | None = None

    # ------------------------------------------------------------------------------ action conversion
    def decode(self, action: np.ndarray | Sequence[int]) -> Action:
        """The fleet's Action for a gym action (primitive index, row, col, angle bin)."""
        k, row, col, rot = (int(v) for v in action)
        return Action(self.primitives[k], row, col, rot * 2.0 * math.pi / self.num_rotations, 0.0)

    def encode(self, action: Action) -> np.ndarray:
        """The gym action nearest a fleet Action (its angle rounded to the nearest bin), e.g. the oracle's."""
        rot = round(action.angle_rad / (2.0 * math.pi / self.num_rotations)) % self.num_rotations
        return np.array([self.primitives.index(action.primitive), action.row, action.col, rot], dtype=np.int64)

    # ------------------------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        """A new scene built from `seed` (SimEnv's seed); seed None draws one from the env's np_random."""
        super().reset(seed=seed)
        scene_seed = seed if seed is not None else int(self.np_random.integers(2**31 - 1))
        self._last = self.sim.reset(scene_seed)
        return self._observation(self._last), {"seed": scene_seed, "progress": float(self.sim.progress)}

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        result = self.sim.step(self.decode(action))
        self._last = result.observation
        info: dict[str, Any] = {
            **result.info, "success": bool(result.success), "is_success": result.done_reason == "done",
            "done_reason": result.done_reason, "progress": float(result.progress_after), "detail": result.detail,
        }
        terminated = result.done_reason in TERMINAL_REASONS
        truncated = result.done_reason == "step_limit"
        return self._observation(result.observation), float(result.reward), terminated, truncated, info

    def render(self) -> np.ndarray | None:  # type: ignore[override]
        """rgb_array: the camera's last colour image (uint8 H x W x 3, the camera's size); else None."""
        if self.render_mode != "rgb_array" or self._last is None:
            return None
        image = self._last.camera_color
        return image.copy() if image is not None else self.sim.render().color

    def close(self) -> None:
        self.sim.close()

    def _observation(self, obs: Observation) -> dict[str, Any]:
        # Copies: the caller may write into them; SimEnv still acts on its own.
        return {"color": obs.color_hm.copy(), "depth": np.clip(obs.depth_hm, 0.0, self._depth_max),
                "holding": int(obs.holding)}


def register_envs() -> None:
    """Register the three task ids with Gymnasium (idempotent)."""
    for name, kind in TASKS.items():
        env_id = f"romannet/{name}-v0"
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point="romannet.gym_env:RoManNetEnv", kwargs={"task": kind})


register_envs()
