"""SimEnv: the PyBullet simulator behind common.interfaces.Env (reset / step / close).

The robot is the Panda arm (sim.robot = "arm") or the floating Panda hand ("gripper", see gripper.py).

One PyBullet DIRECT client per SimEnv. Deterministic: the same seed gives the same scene, and the same
actions then give the same outcomes (fixed time step, fixed call order, the episode's own numpy Generator).

Per step: refuse what cannot be attempted, turn the pixel into a world pose with
common.action.pixel_to_position on the current depth heightmap, run the primitive (X as it reports it:
push moved an object > push_moved_threshold_m, pick holds an object after the lift), capture a new
observation, and judge the step by the rules a real robot applies too (common.episode_rules: the place
rule, P, R_tp, the failure streak, the done reason). The one thing measured differently: the task is
complete by the objects' true poses (none left in the workspace, or a stack of the goal's height).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from romannet.common.action import (
    PLACE_PATCH_RADIUS_M,
    PUSH_PATCH_RADIUS_M,
    Action,
    patch_max,
    pixel_to_position,
    place_position,
)
from romannet.common.config import CameraConfig, Config, RewardConfig, TaskConfig, WorkspaceConfig
from romannet.common.config_sim import SimConfig
from romannet.common.episode_rules import Measure, done_reason, goal_reached, judge_step, measure, refusal
from romannet.common.interfaces import Observation, StepResult
from romannet.common.stack import stack_height

from .gripper import FloatingGripper
from .primitives import PrimitiveResult, Primitives
from .robot import Hand, PandaArm
from .scene import Frame, Scene
from .tasks import build_scene, object_specs, objects_in_workspace, stack_height_from_poses, task_def

log = logging.getLogger(__name__)

PUSH_CLEARANCE_M = 0.005  # fingertips this far above the highest point within PUSH_PATCH_RADIUS_M of the pixel
PUSH_MIN_HEIGHT_M = 0.01  # ... and never lower than this above the table (objects are >= 2.5 cm tall)
# The open fingers reach 4 cm (plus their width) either side of a pick's pixel: the descent slows down above
# the highest point within this radius, not only above the pixel, so a finger landing on a neighbouring
# object meets it slowly (at full speed it threw the object: measured).
PICK_REACH_RADIUS_M = 0.05
# ... and the hand, 21 cm long along the closing axis, has its underside 4.6 cm above the fingertips.
HAND_REACH_RADIUS_M = 0.11
HAND_ABOVE_TIPS_M = 0.045


class SimEnv:
    """The paper's tasks in PyBullet with a Panda arm; see the module docstring."""

    def __init__(self, workspace: WorkspaceConfig | None = None, camera: CameraConfig | None = None,
                 task: TaskConfig | None = None, reward: RewardConfig | None = None,
                 sim: SimConfig | None = None):
        self.ws = workspace or WorkspaceConfig()
        self.cam = camera or CameraConfig()
        self.task = task or TaskConfig()
        self.reward_cfg = reward or RewardConfig()
        self.sim = sim or SimConfig()
        self.primitives: tuple[str, ...] = self.task.primitives
        self.paused = ""  # Env: a simulation never stops for an operator
        self.task_def = task_def(self.task, self.sim)
        self.scene = Scene(self.ws, self.cam, self.sim)
        self.arm: Hand | None = None  # the Panda arm, or the floating hand (sim.robot = "gripper")
        self.prims: Primitives | None = None
        self._next_seed = 0
        self._episode_over = True

    @classmethod
    def from_config(cls, cfg: Config, sim: SimConfig | None = None) -> SimEnv:
        """Build from the root Config's sections (`sim` overrides cfg.sim when given)."""
        return cls(cfg.workspace, cfg.camera, cfg.task, cfg.reward, sim or cfg.sim)

    # ------------------------------------------------------------------------------------- lifecycle
    def reset(self, seed: int | None = None) -> Observation:
        """New episode: a fresh world built from `seed` (None: the previous seed + 1, starting at 0)."""
        if seed is None:
            seed = self._next_seed
        self._next_seed = seed + 1
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.scene.reset_world()
        if self.arm is not None:
            self.arm.close()
        robot_cls = PandaArm if self.sim.robot == "arm" else FloatingGripper
        self.arm = robot_cls(self.scene.client, self.sim)
        self.scene.robot_id = self.arm.body_id
        self.prims = Primitives(self.scene, self.arm, self.sim)
        build_scene(self.scene, self.task_def, object_specs(self.task_def, self.sim, self.ws, self.rng), self.rng)
        self.holding, self.held_body, self.hang_m = False, None, 0.0
        self.steps = 0
        self.consecutive_failures = 0
        self.picks = self.successful_picks = 0
        self._episode_over = False
        return self.observe_start()

    def observe_start(self) -> Observation:
        """Observe the scene as it is now as the episode's start (P's reference); reset() ends with it, and
        tests that build a scene by hand after reset() call it again."""
        self.obs = self._observe()
        self.depth_start = self.obs.depth_hm
        self.measured = self._measure(self.obs.depth_hm)
        return self.obs

    def close(self) -> None:
        """Release the PyBullet clients. Idempotent."""
        if self.arm is not None:
            self.arm.close()
        self.scene.close()

    def try_resume(self) -> bool:
        """Env: the simulator is never paused, so it can always act."""
        return True

    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Env: the simulated camera's pose and intrinsics."""
        return self.scene.T_world_cam, self.scene.intrinsics

    def __enter__(self) -> SimEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------------------------- observation
    def render(self) -> Frame:
        """One camera frame of the current scene (depth noise drawn from the episode's rng, if configured)."""
        # The robot is left out of the render when it cannot be seen (at home): same image, ~25 ms less.
        return self.scene.render(self.rng, cull=(self.arm.body_id,) if self.arm is not None else ())

    def _observe(self) -> Observation:
        t0 = time.perf_counter()
        frame = self.render()
        color_hm, depth_hm = self.scene.heightmaps(frame)
        self.last_observe_s = time.perf_counter() - t0  # wall-clock, for the benchmark only
        return Observation(color_hm, depth_hm, self.holding, frame.color, frame.depth_m)

    def _measure(self, depth_hm: np.ndarray) -> Measure:
        """Stack height, occupied share and P of a heightmap of this episode (once per observation)."""
        return measure(depth_hm, self.depth_start, self.task, self.reward_cfg)

    @property
    def progress(self) -> float:
        """Task progress P of the current observation."""
        return self.measured.progress

    def stack_height_hm(self, depth_hm: np.ndarray) -> int:
        """Stack height in cubes measured on a depth heightmap (what the reward uses, as on a real robot)."""
        return stack_height(depth_hm, self.task.cube_size_m)

    def stack_height_gt(self) -> int:
        """Ground-truth stack height in cubes from object poses (metrics and tests); the held cube excluded."""
        return stack_height_from_poses(self.scene, self.task.cube_size_m, exclude=self.held_body)

    # ------------------------------------------------------------------------------------------ step
    def _execute(self, action: Action) -> PrimitiveResult:
        assert self.prims is not None
        x, y, z = pixel_to_position(action.row, action.col, self.obs.depth_hm, self.ws)
        if action.primitive == "push":
            z_push = max(patch_max(self.obs.depth_hm, action.row, action.col, PUSH_PATCH_RADIUS_M, self.ws.resolution_m) + PUSH_CLEARANCE_M,
                         PUSH_MIN_HEIGHT_M)
            return self.prims.push(x, y, z_push + self.ws.z_min_m, action.angle_rad)
        if action.primitive == "pick":
            hm, res = self.obs.depth_hm, self.ws.resolution_m
            z_reach = max(patch_max(hm, action.row, action.col, PICK_REACH_RADIUS_M, res),
                          patch_max(hm, action.row, action.col, HAND_REACH_RADIUS_M, res) - HAND_ABOVE_TIPS_M
                          ) + self.ws.z_min_m
            return self.prims.pick(x, y, z, action.angle_rad, remove_held=self.task_def.remove_picked,
                                   z_contact_m=z_reach)
        if self.prims.held_body() != self.held_body:  # the object slipped out on the way
            return PrimitiveResult(False, "dropped", 0)
        z_place = patch_max(self.obs.depth_hm, action.row, action.col, PLACE_PATCH_RADIUS_M,
                            self.ws.resolution_m) + self.ws.z_min_m
        x, y = place_position(self.obs.depth_hm, action.row, action.col, self.ws, self.task.cube_size_m,
                              self.task.place_on_top_centre)
        return self.prims.place(x, y, z_place, action.angle_rad, self.hang_m)

    def step(self, action: Action) -> StepResult:
        """Execute one primitive; failures (unreachable, nothing grasped, ...) come back as success False."""
        if self._episode_over:
            raise RuntimeError("the episode is over (or never started): call reset() first")
        self.steps += 1
        before = self.measured
        reason = refusal(action, self.primitives, self.holding, self.obs.depth_hm.shape)
        result = PrimitiveResult(False, reason, 0) if reason else self._execute(action)
        if action.primitive == "pick" and not reason:
            self.picks += 1
            if result.success and not self.task_def.remove_picked:  # (clutter: the pick removed it already)
                self.holding, self.held_body, self.hang_m = True, result.held_body, result.hang_m
            self.successful_picks += int(result.success)
        if action.primitive == "place" and not reason:
            self.holding, self.held_body, self.hang_m = False, None, 0.0

        unstable = result.unstable or self.scene.instability()
        self.obs = self._observe()
        self.measured = self._measure(self.obs.depth_hm)
        judged = judge_step(action.primitive, result.success, result.reason, before, self.measured,
                            self.consecutive_failures, self.reward_cfg)
        self.consecutive_failures = judged.consecutive_failures

        in_workspace, height_gt = objects_in_workspace(self.scene), self.stack_height_gt()  # once per step
        ended = done_reason(goal_reached(self.task, height_gt, in_workspace == 0), self.consecutive_failures,
                            self.steps, self.sim, unstable)
        self._episode_over = bool(ended)
        if unstable:
            log.warning("episode ended unstable (seed %d, step %d): %s", self.seed, self.steps, unstable)
        info: dict[str, float | int | str | bool] = {
            "seed": self.seed, "step": self.steps, "physics_steps": result.steps,
            "objects_in_workspace": in_workspace,
            "stack_height_gt": height_gt, "stack_height_hm": self.measured.stack_height,
            "moved_m": result.moved_m, "consecutive_failures": self.consecutive_failures,
            "unstable": unstable,
        }
        if result.grasp is not None:  # why a pick that closed held or failed (grasp_check.py)
            info.update(result.grasp.info(result.success, self.sim.grasp_min_gap_m))
        return StepResult(self.obs, judged.success, judged.progress_before, judged.progress_after, judged.reward,
                          bool(ended), ended, judged.detail, info)
